"""The web interface (``orthonav serve``): maps on a Leaflet page over their orthophoto tiles,
missions started from the map and followed live, past runs opened and compared.

Needs the ``web`` extra (FastAPI, uvicorn, rio-tiler).
"""

from orthonav.web.app import WebSettings, create_app
from orthonav.web.server import is_loopback, make_server

__all__ = ["WebSettings", "create_app", "is_loopback", "make_server"]
