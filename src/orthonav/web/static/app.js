/* orthonav web page: plan a mission on the map, follow it live, open and compare past runs.
 * Everything shown comes from the JSON API; this script only draws it. Server text is always
 * inserted as text (never as HTML). */
"use strict";

const STATUS_COLOURS = {fixed: "#2ca02c", "dead reckoning": "#ff9f1c", lost: "#d62728", uninitialised: "#888"};
const COMPARE_COLOURS = ["#e377c2", "#17becf", "#bcbd22", "#9467bd", "#8c564b", "#7f7f7f", "#1f77b4", "#ff7f0e"];
const TERMINAL = ["done", "failed", "cancelled"];

const $ = (id) => document.getElementById(id);

function el(tag, text, attrs) {
  const node = document.createElement(tag);
  if (text !== undefined && text !== null) node.textContent = String(text);
  Object.entries(attrs || {}).forEach(([k, v]) => node.setAttribute(k, v));
  return node;
}

function fmt(value, digits) {
  if (value === null || value === undefined) return "";
  return typeof value === "number" ? value.toFixed(digits === undefined ? 1 : digits) : String(value);
}

async function api(path, options) {
  const response = await fetch(path, options);
  const body = await response.json().catch(() => ({}));
  if (!response.ok) throw new Error(body.detail || `${response.status} ${response.statusText}`);
  return body;
}

function showMessage(id, text, kind) {
  const box = $(id);
  box.textContent = text || "";
  box.className = `message ${kind || ""}`;
}

// --- the map --------------------------------------------------------------------------------

const map = L.map("map", {preferCanvas: true, zoomSnap: 0.25}).setView([0, 0], 2);
const overlays = {
  true: L.polyline([], {color: "#1f77b4", weight: 5, opacity: 0.8}),
  estimated: L.featureGroup(),
  ins: L.polyline([], {color: "#111", weight: 2, opacity: 0.9, dashArray: "6 6"}),
  fixes: L.featureGroup(),
  compare: L.featureGroup(),
};
Object.values(overlays).forEach((layer) => layer.addTo(map));
const layerControl = L.control.layers(null, {
  "true track": overlays.true, "estimated track": overlays.estimated, "INS alone": overlays.ins,
  "fixes": overlays.fixes, "compared runs": overlays.compare,
}).addTo(map);
L.control.scale({imperial: false}).addTo(map);

const state = {
  maps: {}, mapName: null, ortho: null, picking: "start", start: null, target: null,
  run: null, events: null, estSegments: [], nav: [], steps: [],
};

function maxNativeZoom(info) {
  const gsd = info.summary.work_gsd_m;
  const lat = (info.bounds[0][0] + info.bounds[1][0]) / 2;
  const z = Math.log2(156543.034 * Math.cos((lat * Math.PI) / 180) / gsd);
  return Math.max(1, Math.min(22, Math.ceil(z)));
}

function showMap(name, fit) {
  const info = state.maps[name];
  if (!info || info.error) return;
  state.mapName = name;
  $("map-select").value = name;
  if (state.ortho) {
    layerControl.removeLayer(state.ortho);
    map.removeLayer(state.ortho);
  }
  state.ortho = L.tileLayer(`/api/maps/${encodeURIComponent(name)}/tiles/{z}/{x}/{y}.png`, {
    bounds: info.bounds, maxZoom: 22, maxNativeZoom: maxNativeZoom(info), attribution: "orthophoto: " + name,
  }).addTo(map);
  state.ortho.bringToBack();
  layerControl.addBaseLayer(state.ortho, "orthophoto");
  if (fit) map.fitBounds(info.bounds);
  const s = info.summary;
  $("map-info").textContent = `${s.work_size_px} px, ${fmt(s.work_gsd_m, 2)} m/px, ${s.area_km2} km², ` +
    `${info.backend}, nominal ${s.nominal_alt_m} m`;
  $("fix-source").querySelector("option[value=map]").textContent = `keypoints (${info.backend})`;
}

async function loadMaps(select) {
  const maps = await api("/api/maps");
  const selectBox = $("map-select");
  selectBox.replaceChildren();
  state.maps = {};
  maps.forEach((info) => {
    state.maps[info.name] = info;
    const option = el("option", info.error ? `${info.name} (cannot open)` : info.name, {value: info.name});
    if (info.error) option.disabled = true;
    selectBox.append(option);
  });
  const usable = maps.filter((m) => !m.error).map((m) => m.name);
  const name = usable.includes(select) ? select : usable.includes(state.mapName) ? state.mapName : usable[0];
  if (name) showMap(name, name !== state.mapName || select !== undefined);
  else showMessage("mission-message", "No map package yet: upload a GeoTIFF below to build one.", "");
}

// --- start and target -----------------------------------------------------------------------

const markers = {
  start: L.marker([0, 0], {draggable: true, title: "start"}),
  target: L.marker([0, 0], {draggable: true, title: "target"}),
};
const startZone = L.circle([0, 0], {radius: 100, color: "#1f77b4", weight: 1, fillOpacity: 0.1});
markers.start.bindTooltip("start", {permanent: true, direction: "right"});
markers.target.bindTooltip("target", {permanent: true, direction: "right"});

function setPoint(which, latlng, fromInput) {
  state[which] = latlng;
  markers[which].setLatLng(latlng).addTo(map);
  if (which === "start") startZone.setLatLng(latlng).setRadius(Number($("start-zone").value) || 100).addTo(map);
  if (!fromInput) {
    $(`${which}-lat`).value = latlng.lat.toFixed(6);
    $(`${which}-lon`).value = latlng.lng.toFixed(6);
  }
}

function setPicking(which) {
  state.picking = which;
  $("pick-start").classList.toggle("active", which === "start");
  $("pick-target").classList.toggle("active", which === "target");
}

map.on("click", (event) => {
  setPoint(state.picking, event.latlng);
  if (state.picking === "start") setPicking("target");
});
["start", "target"].forEach((which) => {
  markers[which].on("drag", (event) => setPoint(which, event.target.getLatLng()));
  $(`pick-${which}`).addEventListener("click", () => setPicking(which));
  [`${which}-lat`, `${which}-lon`].forEach((id) => $(id).addEventListener("change", () => {
    const lat = parseFloat($(`${which}-lat`).value), lon = parseFloat($(`${which}-lon`).value);
    if (Number.isFinite(lat) && Number.isFinite(lon)) setPoint(which, L.latLng(lat, lon), true);
  }));
});
$("start-zone").addEventListener("change", () => startZone.setRadius(Number($("start-zone").value) || 100));

// --- mission form ---------------------------------------------------------------------------

function number(id) {
  const text = $(id).value.trim();
  return text === "" ? null : Number(text);
}

function missionRequest() {
  const body = {
    map: state.mapName,
    start: {lat: number("start-lat"), lon: number("start-lon")},
    target: {lat: number("target-lat"), lon: number("target-lon")},
    fix_source: $("fix-source").value,
    frames_from: $("frames-from").value || null,
    speed_mps: number("speed"), alt_agl_m: number("altitude"), step_s: number("step"),
    max_time_s: number("max-time"), start_zone_m: number("start-zone"), arrival_radius_m: number("arrival"),
    imu: $("imu").value, gnss_loss_s: number("gnss-loss"), seed: number("seed"),
  };
  Object.keys(body).forEach((key) => body[key] === null && key !== "frames_from" && delete body[key]);
  return body;
}

$("mission-form").addEventListener("submit", async (event) => {
  event.preventDefault();
  if (!state.mapName) return showMessage("mission-message", "Choose or build a map first.", "error");
  showMessage("mission-message", "starting...", "");
  try {
    const run = await api("/api/runs", {
      method: "POST", headers: {"Content-Type": "application/json"}, body: JSON.stringify(missionRequest()),
    });
    showMessage("mission-message", `mission ${run.id} ${run.state}`, "ok");
    if (state.start && state.target) map.fitBounds(L.latLngBounds([state.start, state.target]).pad(0.3));
    followRun(run.id);
    loadRuns();
  } catch (error) {
    showMessage("mission-message", error.message, "error");
  }
});

// --- a run: tracks, fixes, frame, error plot, log ---------------------------------------------

function clearRun() {
  if (state.events) state.events.close();
  state.events = null;
  overlays.true.setLatLngs([]);
  overlays.ins.setLatLngs([]);
  overlays.estimated.clearLayers();
  overlays.fixes.clearLayers();
  state.estSegments = [];
  state.nav = [];
  state.steps = [];
  $("step-log").tBodies[0].replaceChildren();
  $("run-summary").replaceChildren();
  $("run-files").replaceChildren();
  $("frame").removeAttribute("src");
  $("frame").classList.remove("matches");
  $("frame-info").textContent = "";
  $("frame-step").textContent = "";
  drawErrors();
}

function addNav(record) {
  state.nav.push(record);
  overlays.true.addLatLng([record.true_lat, record.true_lon]);
  overlays.ins.addLatLng([record.ins_lat, record.ins_lon]);
  const point = [record.nav_lat, record.nav_lon];
  const last = state.estSegments[state.estSegments.length - 1];
  if (last && last.status === record.nav_status) {
    last.line.addLatLng(point);
  } else {
    // A new colour starts where the previous one ended, so the track stays continuous.
    const start = last ? last.line.getLatLngs().slice(-1) : [];
    const line = L.polyline([...start, point], {color: STATUS_COLOURS[record.nav_status] || "#888", weight: 2});
    overlays.estimated.addLayer(line);
    state.estSegments.push({status: record.nav_status, line});
  }
  drawErrors();
}

function fixMarker(step) {
  if (step.accepted) {
    const colour = step.fused ? STATUS_COLOURS.fixed : STATUS_COLOURS["dead reckoning"];
    const verdict = step.fused ? "fused" : `not fused: ${step.filter.reason}`;
    return L.circleMarker([step.est_lat, step.est_lon], {radius: 3, weight: 1, color: colour, fillOpacity: 0.9})
      .bindTooltip(`step ${step.step}: fix error ${fmt(step.error_m)} m, ${verdict}`);
  }
  // A rejected frame has no position: it is marked where it was taken.
  return L.circleMarker([step.true_lat, step.true_lon], {radius: 4, weight: 1, color: STATUS_COLOURS.lost, fillOpacity: 0.9})
    .bindTooltip(`step ${step.step}: rejected: ${step.reason}`);
}

function addStep(step) {
  state.steps.push(step);
  overlays.fixes.addLayer(fixMarker(step));
  const row = el("tr", null, {class: step.accepted ? (step.fused ? "fused" : "accepted") : "rejected"});
  const filter = step.fused ? "fused" : step.filter ? step.filter.reason : "";
  [step.step, fmt(step.time_s, 0), step.accepted ? "accepted" : "rejected", step.reason, fmt(step.error_m),
    step.fix ? step.fix.inliers : "", filter, fmt(step.nav_error_m), fmt(step.nav_sigma_m), step.nav_status,
  ].forEach((value) => row.append(el("td", value)));
  row.addEventListener("click", () => showFrame(step, true));
  const body = $("step-log").tBodies[0];
  body.append(row);
  body.parentElement.parentElement.scrollTop = body.parentElement.scrollHeight;
  showFrame(step, false);
  drawErrors();
}

function showFrame(step, pan) {
  // The matches picture (frame | map orthophoto, a line per inlier) where the fix has point
  // matches; the bare frame otherwise (dense correlation, or no homography to keep inliers of).
  const url = step.matches_url || step.frame_url;
  if (url) $("frame").src = url;
  $("frame").classList.toggle("matches", Boolean(step.matches_url));
  $("frame").alt = step.matches_url ? "camera frame and its inlier matches on the map" : "current camera frame";
  $("frame-step").textContent = `step ${step.step}, t = ${fmt(step.time_s, 0)} s`;
  const q = (step.fix && step.fix.quality) || {};
  const parts = [
    step.accepted ? `fix accepted (${fmt(step.error_m)} m from truth)` : `rejected: ${step.reason}`,
    `keypoints ${q.keypoints ?? "-"}, matches ${q.matches ?? "-"}, inliers ${q.inliers ?? "-"}`,
    q.inlier_ratio !== undefined ? `inlier ratio ${fmt(q.inlier_ratio, 2)}` : "",
    step.fix && step.fix.rmse !== null && step.fix.rmse !== undefined ? `RMSE ${fmt(step.fix.rmse, 2)} px` : "",
  ];
  if (step.frame_url && !step.matches_url) parts.push("no point matches to draw");
  $("frame-info").textContent = parts.filter(Boolean).join(" · ");
  if (pan) map.panTo([step.true_lat, step.true_lon]);
}

function drawErrors() {
  const canvas = $("error-plot");
  const ctx = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height, pad = 28;
  ctx.clearRect(0, 0, w, h);
  const nav = state.nav;
  const fixes = state.steps.filter((s) => s.accepted && s.error_m !== null);
  if (!nav.length) return;
  const tMax = Math.max(nav[nav.length - 1].time_s, 1);
  const values = nav.map((r) => Math.max(r.nav_error_m, 3 * r.nav_sigma_m)).concat(fixes.map((s) => s.error_m));
  const yMax = Math.max(5, Math.min(Math.max(...values), 5 * Math.max(...nav.map((r) => r.nav_error_m), 1)));
  const x = (t) => pad + ((w - pad - 6) * t) / tMax;
  const y = (v) => h - pad + 8 - ((h - pad) * Math.min(v, yMax)) / yMax;
  ctx.strokeStyle = "#999";
  ctx.fillStyle = "#444";
  ctx.font = "10px sans-serif";
  ctx.beginPath();
  ctx.moveTo(pad, 4);
  ctx.lineTo(pad, h - pad + 8);
  ctx.lineTo(w - 4, h - pad + 8);
  ctx.stroke();
  ctx.fillText(fmt(yMax, 0), 2, 12);
  ctx.fillText("0", 14, h - pad + 8);
  ctx.fillText(`${fmt(tMax, 0)} s`, w - 40, h - 4);
  const line = (key, scale, colour, dash) => {
    ctx.setLineDash(dash);
    ctx.strokeStyle = colour;
    ctx.beginPath();
    nav.forEach((r, i) => (i ? ctx.lineTo : ctx.moveTo).call(ctx, x(r.time_s), y(scale * r[key])));
    ctx.stroke();
    ctx.setLineDash([]);
  };
  line("nav_sigma_m", 3, "#aaa", [4, 3]);
  line("nav_error_m", 1, "#d62728", []);
  ctx.fillStyle = STATUS_COLOURS.fixed;
  fixes.forEach((s) => ctx.fillRect(x(s.time_s) - 2, y(s.error_m) - 2, 4, 4));
  ctx.fillStyle = "#444";
  ctx.fillText("navigation error, 3-sigma (dashed), fix errors (dots)", pad + 4, 12);
}

function showState(run) {
  state.run = run;
  const request = run.request || {};
  $("run-title").textContent = `Run ${run.id}`;
  const texts = {
    failed: `failed: ${run.error}`,
    done: `done: ${run.end_reason}`,
    cancelled: run.end_reason && run.end_reason !== "cancelled" ? `cancelled: ${run.end_reason}` : "cancelled",
    running: run.cancel_requested ? "running, stopping at the next frame" : "running",
  };
  const text = texts[run.state] || run.state;
  const kind = run.state === "failed" ? "error" : run.state === "done" ? "ok" : "";
  $("cancel-run").hidden = TERMINAL.includes(run.state) || Boolean(run.cancel_requested);
  showMessage("run-status", `${request.map || ""} · ${text}`, kind);
  if ($("mission-message").textContent.includes(run.id)) showMessage("mission-message", `mission ${run.id} ${run.state}`, kind);
  const table = $("run-summary");
  table.replaceChildren();
  const summary = run.summary || {};
  ["arrived", "arrived_true", "end_reason", "steps", "flight_time_s", "fix_rate", "fused_rate",
    "nav_error_median_m", "nav_error_max_m", "error_median_m", "ins_only_error_end_m", "true_distance_to_target_m",
  ].filter((key) => key in summary).forEach((key) => {
    const row = el("tr");
    row.append(el("th", key), el("td", fmt(summary[key], 2)));
    table.append(row);
  });
  if (TERMINAL.includes(run.state)) loadFiles(run.id);
}

async function loadFiles(runId) {
  const files = await api(`/api/runs/${runId}/files`);
  const list = $("run-files");
  list.replaceChildren();
  files.filter((f) => !f.path.startsWith("frames/")).forEach((file) => {
    const url = `/api/runs/${runId}/files/${file.path}`;
    const item = el("li");
    item.append(el("a", file.path, {href: url, download: file.path}), el("span", ` ${fmt(file.size_bytes / 1024, 0)} kB`));
    if (file.path.endsWith(".png")) {
      const link = el("a", null, {href: url, target: "_blank"});
      link.append(el("img", null, {src: url, alt: file.path, class: "thumb"}));
      item.append(link);
    }
    list.append(item);
  });
}

async function cancelRun() {
  if (!state.run) return;
  try {
    showState({...state.run, ...(await api(`/api/runs/${state.run.id}/cancel`, {method: "POST"}))});
  } catch (error) {
    showMessage("run-status", error.message, "error");
  }
}

function followRun(runId) {
  clearRun();
  const source = new EventSource(`/api/runs/${runId}/events`);
  state.events = source;
  source.addEventListener("nav", (event) => addNav(JSON.parse(event.data)));
  source.addEventListener("step", (event) => addStep(JSON.parse(event.data)));
  source.addEventListener("state", (event) => {
    const run = JSON.parse(event.data);
    showState(run);
    if (TERMINAL.includes(run.state)) {
      source.close();
      loadRuns();
    }
  });
  source.onerror = () => source.readyState === EventSource.CLOSED || showMessage("run-status", "connection lost; retrying", "error");
}

async function openRun(runId) {
  clearRun();
  try {
    const run = await api(`/api/runs/${runId}`);
    if (run.request && run.request.map && run.request.map !== state.mapName) showMap(run.request.map, true);
    if (!TERMINAL.includes(run.state)) return followRun(runId);
    run.nav.forEach(addNav);
    run.steps.forEach(addStep);
    showState(run);
    if (overlays.true.getLatLngs().length) map.fitBounds(overlays.true.getBounds().pad(0.3));
  } catch (error) {
    showMessage("run-status", error.message, "error");
  }
}

// --- runs list and comparison -------------------------------------------------------------------

async function loadRuns() {
  const runs = await api("/api/runs");
  const body = $("runs-table").tBodies[0];
  body.replaceChildren();
  runs.forEach((run) => {
    const summary = run.summary || {};
    const row = el("tr", null, {"data-run": run.id});
    const box = el("input", null, {type: "checkbox", "aria-label": `select ${run.id}`});
    box.addEventListener("click", (event) => event.stopPropagation());
    const check = el("td");
    check.append(box);
    row.append(check, el("td", run.id), el("td", (run.request || {}).map), el("td", run.state, {title: run.error || ""}),
      el("td", fmt(summary.nav_error_median_m)), el("td", summary.arrived === undefined ? "" : summary.arrived_true ? "yes" : "no"));
    row.addEventListener("click", () => openRun(run.id));
    body.append(row);
  });
}

async function compareRuns() {
  const ids = [...$("runs-table").querySelectorAll("tbody tr")]
    .filter((row) => row.querySelector("input").checked).map((row) => row.dataset.run);
  const box = $("compare");
  box.replaceChildren();
  overlays.compare.clearLayers();
  if (ids.length < 2) return box.append(el("p", "Select two or more runs to compare.", {class: "message error"}));
  const query = ids.map((id) => `run=${encodeURIComponent(id)}`).join("&");
  const {runs} = await api(`/api/compare?${query}`);
  const keys = ["state", "fix_source", "arrived", "arrived_true", "steps", "fix_rate", "fused_rate",
    "nav_error_median_m", "nav_error_max_m", "ins_only_error_end_m", "true_distance_to_target_m"];
  const table = el("table", null, {class: "kv compare"});
  const head = el("tr");
  head.append(el("th", "run"));
  // Run ids end with their time and a random suffix; that part tells them apart.
  runs.forEach((run, i) => head.append(el("th", run.id.slice(-13), {title: run.id, style: `color:${COMPARE_COLOURS[i % 8]}`})));
  table.append(head);
  keys.forEach((key) => {
    const row = el("tr");
    row.append(el("th", key));
    runs.forEach((run) => {
      const value = key in (run.summary || {}) ? run.summary[key] : key in run ? run[key] : (run.request || {})[key];
      row.append(el("td", fmt(value, 2)));
    });
    table.append(row);
  });
  box.append(el("h3", "Comparison"), table);
  // Each compared run's estimated track, in its column's colour.
  for (const [i, id] of ids.entries()) {
    const run = await api(`/api/runs/${id}`);
    overlays.compare.addLayer(L.polyline(run.nav.map((r) => [r.nav_lat, r.nav_lon]),
      {color: COMPARE_COLOURS[i % 8], weight: 2}).bindTooltip(`${id} (estimate)`));
  }
}

$("refresh-runs").addEventListener("click", loadRuns);
$("cancel-run").addEventListener("click", cancelRun);
$("frame").addEventListener("click", () => $("frame").src && window.open($("frame").src, "_blank", "noopener"));
$("compare-runs").addEventListener("click", () => compareRuns().catch((e) => showMessage("run-status", e.message, "error")));
$("map-select").addEventListener("change", (event) => showMap(event.target.value, true));

// --- upload and build ---------------------------------------------------------------------------

function upload(file, name) {
  return new Promise((resolve, reject) => {
    const request = new XMLHttpRequest();
    request.open("PUT", `/api/orthophotos/${encodeURIComponent(name)}`);
    request.setRequestHeader("Content-Type", "image/tiff");
    request.upload.onprogress = (event) => event.lengthComputable && ($("upload-progress").value = event.loaded / event.total);
    request.onload = () => {
      const body = JSON.parse(request.responseText || "{}");
      request.status < 300 ? resolve(body) : reject(new Error(body.detail || `upload failed (${request.status})`));
    };
    request.onerror = () => reject(new Error("upload failed: connection closed (too large?)"));
    request.send(file);
  });
}

async function followBuild(job) {
  for (;;) {
    job = await api(`/api/jobs/${job.id}`);
    if (job.tiles_total) $("build-progress").value = job.tiles_done / job.tiles_total;
    showMessage("upload-message", `map ${job.map_name}: ${job.state} (${job.tiles_done}/${job.tiles_total ?? "?"} tiles)`, "");
    if (job.state === "done") return job;
    if (job.state === "failed") throw new Error(`map ${job.map_name}: build failed: ${job.error}`);
    await new Promise((resolve) => setTimeout(resolve, 500));
  }
}

$("upload-form").addEventListener("submit", async (event) => {
  event.preventDefault();
  const file = $("upload-file").files[0];
  const name = $("upload-name").value.trim() || (file ? file.name.replace(/\.tiff?$/i, "") : "");
  if (!file) return showMessage("upload-message", "Choose a GeoTIFF file.", "error");
  $("upload-progress").value = 0;
  $("build-progress").value = 0;
  try {
    showMessage("upload-message", "uploading...", "");
    await upload(file, name);
    $("upload-progress").value = 1;
    await loadOrthophotos();
    if (!$("upload-build").checked) return showMessage("upload-message", `orthophoto ${name} uploaded`, "ok");
    const [width, height] = $("build-size").value.split("x").map(Number);
    const job = await api("/api/maps", {
      method: "POST", headers: {"Content-Type": "application/json"},
      body: JSON.stringify({name, orthophoto: name, altitude_m: number("build-altitude"), hfov_deg: number("build-hfov"),
        width, height, features: $("build-features").value}),
    });
    await followBuild(job);
    $("build-progress").value = 1;
    showMessage("upload-message", `map ${name} built`, "ok");
    await loadMaps(name);
  } catch (error) {
    showMessage("upload-message", error.message, "error");
  }
});

// --- start-up -------------------------------------------------------------------------------------

async function loadOrthophotos() {
  const select = $("frames-from");
  const current = select.value;
  select.replaceChildren(el("option", "the map's orthophoto", {value: ""}));
  (await api("/api/orthophotos")).forEach((o) => select.append(el("option", o.name, {value: o.name})));
  select.value = current;
}

async function loadOptions() {
  const options = await api("/api/options");
  Object.entries(options.fix_sources).forEach(([key, text]) => $("fix-source").append(el("option", key === "map" ? "keypoints" : key, {value: key, title: text})));
  options.imu.forEach((name) => $("imu").append(el("option", name, {value: name})));
  $("imu").value = "consumer";
  options.features.forEach((name) => $("build-features").append(el("option", name, {value: name})));
  $("build-features").value = "orb";
}

window.orthonav = {
  map, overlays, state,
  trackCounts: () => ({
    true: overlays.true.getLatLngs().length,
    estimated: state.nav.length,
    estimatedDrawn: state.estSegments.reduce((n, s) => n + s.line.getLatLngs().length, 0),
    fixes: overlays.fixes.getLayers().length,
    steps: state.steps.length,
  }),
};

(async () => {
  try {
    await loadOptions();
    await Promise.all([loadMaps(), loadOrthophotos(), loadRuns()]);
  } catch (error) {
    showMessage("mission-message", error.message, "error");
  }
})();
