"""Interactive maps in one self-contained HTML file: the orthophoto, fixes with their footprints
and sigma circles, rejected frames with their reason. Leaflet is inlined from the copy that ships
with orthonav, so the page opens offline (no tile server, no CDN)."""

from __future__ import annotations

import base64
import html
import json
from collections.abc import Mapping
from importlib import resources
from pathlib import Path

import cv2

from orthonav.atomic import write_text_atomic
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.mapdb import MapPackage
from orthonav.types import Fix, Prior

LEAFLET = "web/static/vendor/leaflet"


def write_fixes_html(
    package: MapPackage,
    fixes: list[tuple[str, Fix]],
    camera: Camera,
    out: Path,
    priors: Mapping[str, Prior] | None = None,
    title: str = "orthonav fixes",
) -> Path:
    """``out``: a page with the map's preview and every frame: accepted fixes (footprint, sigma
    circle, popup with the numbers) and rejected ones (at their prior, with the reason)."""
    features = [_feature(name, fix, camera, (priors or {}).get(name)) for name, fix in fixes]
    page = _PAGE.format(
        title=html.escape(title),
        leaflet_css=_leaflet("leaflet.css"),
        leaflet_js=_leaflet("leaflet.js"),
        overlay=json.dumps(_overlay(package)),
        features=json.dumps({"type": "FeatureCollection", "features": [f for f in features if f]}),
    )
    write_text_atomic(out, page)
    return out


def _leaflet(name: str) -> str:
    path = resources.files("orthonav").joinpath(f"{LEAFLET}/{name}")
    if not path.is_file():
        raise OrthonavError(f"{LEAFLET}/{name}: missing from the installed package (reinstall orthonav)")
    return path.read_text(encoding="utf-8").replace("</script", "<\\/script")


def _overlay(package: MapPackage) -> dict:
    """The map's preview as a JPEG data URL and its lat/lon bounds (south-west, north-east)."""
    image, grid = package.preview()
    ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])
    if not ok:
        raise OrthonavError(f"{package.path}: its preview cannot be encoded")
    return {
        "url": "data:image/jpeg;base64," + base64.b64encode(jpeg.tobytes()).decode("ascii"),
        "bounds": grid.bounds_latlon(),
    }


def _feature(name: str, fix: Fix, camera: Camera, prior: Prior | None) -> dict | None:
    """One frame as GeoJSON: the footprint polygon of an accepted fix, or the prior's point of a
    rejected one (None when a rejected frame had no position prior to place it at)."""
    if fix.accepted:
        corners = fix.pose.footprint_latlon(camera)
        ring = [[float(lon), float(lat)] for lat, lon in [*corners, corners[0]]]
        properties = {
            "name": name,
            "accepted": True,
            "lat": round(fix.pose.lat, 7),
            "lon": round(fix.pose.lon, 7),
            "sigma_m": round(fix.sigma_m or 0.0, 2),
            "altitude_m": round(fix.pose.alt_agl_m, 1),
            "heading_deg": round(fix.pose.heading_deg, 1),
            "inliers": int(fix.quality.get("inliers", 0)),
        }
        return {
            "type": "Feature",
            "geometry": {"type": "Polygon", "coordinates": [ring]},
            "properties": properties,
        }
    if prior is None or not prior.has_position:
        return None
    properties = {"name": name, "accepted": False, "reason": fix.reason}
    point = {"type": "Point", "coordinates": [prior.lon, prior.lat]}
    return {"type": "Feature", "geometry": point, "properties": properties}


_PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>{title}</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>{leaflet_css}
html, body, #map {{ height: 100%; margin: 0; }}
.legend {{ background: white; padding: 6px 10px; font: 13px sans-serif; line-height: 1.5; }}
</style></head>
<body><div id="map"></div>
<script>{leaflet_js}</script>
<script>
const overlay = {overlay};
const frames = {features};
const map = L.map("map", {{ crs: L.CRS.EPSG3857, zoomSnap: 0.25 }});
L.imageOverlay(overlay.url, overlay.bounds).addTo(map);
const layer = L.geoJSON(frames, {{
  style: f => ({{ color: f.properties.accepted ? "#00c8ff" : "#ff3030", weight: 2, fillOpacity: 0.05 }}),
  pointToLayer: (f, at) => L.circleMarker(at, {{ radius: 6, color: "#ff3030", weight: 3 }}),
  onEachFeature: (f, l) => {{
    const p = f.properties;
    l.bindPopup(p.accepted
      ? `<b>${{p.name}}</b><br>${{p.lat}}, ${{p.lon}}<br>sigma ${{p.sigma_m}} m, ${{p.inliers}} inliers<br>` +
        `altitude ${{p.altitude_m}} m, heading ${{p.heading_deg}} deg`
      : `<b>${{p.name}}</b>: rejected<br>${{p.reason}}`);
    if (p.accepted) {{
      L.circle([p.lat, p.lon], {{ radius: 3 * p.sigma_m, color: "#ffe000", weight: 1 }}).addTo(map);
    }}
  }},
}}).addTo(map);
map.fitBounds(frames.features.length ? layer.getBounds().pad(0.1) : overlay.bounds);
const legend = L.control({{ position: "topright" }});
legend.onAdd = () => {{
  const div = L.DomUtil.create("div", "legend");
  const fixed = frames.features.filter(f => f.properties.accepted).length;
  div.innerHTML = `<b>{title}</b><br>` +
    `<span style="color:#00a0d0">&#9633;</span> footprint of a fix (${{fixed}})` +
    `<br><span style="color:#c8b000">&#9675;</span> its 3 sigma<br>` +
    `<span style="color:#ff3030">&#9679;</span> rejected, at its prior (${{frames.features.length - fixed}})`;
  return div;
}};
legend.addTo(map);
L.control.scale({{ imperial: false }}).addTo(map);
</script></body></html>
"""
