"""Pictures of results, one topic a module, imported from the module that draws them.

``plots`` holds what every figure shares (maps framed in metres, log-metre error axes, the
atomic save); ``mission`` and ``fixes`` draw a mission and ``localize --plot``; ``matches`` a
fix's matches; ``html`` the interactive maps; the rest, each named after its benchmark, that
benchmark's figure.
"""
