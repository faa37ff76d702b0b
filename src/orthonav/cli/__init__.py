"""The ``orthonav`` command line: parse, call the packages, print."""
