"""orthonav: map-based optical navigation for drones when GNSS is unavailable."""

__version__ = "0.1.0"
