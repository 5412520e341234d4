// The insitu web viewer: frames over a WebSocket (JPEG while dragging, PNG once the mouse
// rests), the stored steps and their series from the JSON API. No dependencies.

const token = new URLSearchParams(location.search).get("token");
const withToken = (path) =>
  token ? path + (path.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(token) : path;
const $ = (id) => document.getElementById(id);

const STILL_DELAY_MS = 300; // the still frame follows this long after the last camera change
const view = { angle: 0, elevation: 0, zoom: 1 };
// The first frame's fit zoom is applied (and again after "reset view" or "fit"): the volume
// fills the frame by default.
let fitPending = true;
let shownHeader = null; // the header of the frame on screen (its camera, box, TF)
let legendHash = null; // the TF the legend shows
let steps = []; // from /api/steps
let series = null; // from /api/series
let shownStep = null; // the step on screen (null: none yet)
let socket = null;
let nextId = 1;
let stillTimer = null;
let pendingHeader = null;
let retryMs = 500;

function side() {
  const w = $("frame").clientWidth || 512;
  return Math.max(64, Math.min(768, Math.round(w * (window.devicePixelRatio || 1))));
}

function selectedStep() {
  if ($("follow").checked || steps.length === 0) return null;
  const s = steps[Number($("slider").value)];
  return s ? s.step : null;
}

function selectedRank() {
  const v = $("rank").value;
  return v === "" ? null : Number(v);
}

// While dragging, frames aim at this render time: their side is the largest, up to ¼ of the
// still's area, that the last interactive frame's cost per pixel predicts within it (VTK's
// "desired update rate" idea: resolution traded for latency, never the other way).
const INTERACTIVE_BUDGET_MS = 35;
const MIN_INTERACTIVE_SIDE = 96;
let msPerPixel = null; // render time per pixel of the last interactive frame

function interactiveSide(full) {
  const quarter = Math.round(full / 2);
  if (msPerPixel === null || msPerPixel <= 0) return quarter;
  const fit = Math.floor(Math.sqrt(INTERACTIVE_BUDGET_MS / msPerPixel));
  return Math.max(Math.min(MIN_INTERACTIVE_SIDE, quarter), Math.min(quarter, fit));
}

// The camera each request asked for, by id: a frame is labelled with its own, not with the
// view at the time it arrives (a request may have moved the view since).
const asked = new Map();

// Asks for a frame: interactive (JPEG, at most ¼ area, see `interactiveSide`, from the VDI
// level that matches its size) or still (full PNG from the full VDI).
function request(interactive) {
  if (!socket || socket.readyState !== WebSocket.OPEN) return;
  const full = side();
  const px = interactive ? interactiveSide(full) : full;
  const id = nextId++;
  asked.set(id, { angle: view.angle, elevation: view.elevation, zoom: view.zoom });
  socket.send(JSON.stringify({
    id,
    step: selectedStep(),
    rank: selectedRank(),
    angle: view.angle,
    elevation: view.elevation,
    zoom: view.zoom,
    width: px,
    height: px,
    format: interactive ? "jpeg" : "png",
    quality: 55,
    lod: interactive,
  }));
  clearTimeout(stillTimer);
  if (interactive) stillTimer = setTimeout(() => request(false), STILL_DELAY_MS);
}

function connect() {
  const url = new URL(withToken("api/live"), location.href);
  url.protocol = location.protocol === "https:" ? "wss:" : "ws:";
  socket = new WebSocket(url);
  socket.binaryType = "blob";
  socket.onopen = () => {
    retryMs = 500;
    // How many times the page has (re)connected: visible to scripts and tests.
    document.body.dataset.connections = String(Number(document.body.dataset.connections || 0) + 1);
    $("conn").textContent = "live";
    $("conn").className = "pill up";
    request(false);
  };
  socket.onclose = () => {
    $("conn").textContent = "reconnecting…";
    $("conn").className = "pill down";
    setTimeout(connect, retryMs);
    retryMs = Math.min(retryMs * 2, 8000);
  };
  socket.onmessage = (ev) => {
    if (typeof ev.data === "string") {
      const m = JSON.parse(ev.data);
      if (m.error) {
        $("status").textContent = m.error;
      } else if (m.event === "stored") {
        refresh();
      } else if (m.frame !== undefined) {
        pendingHeader = m;
      }
      return;
    }
    const h = pendingHeader;
    pendingHeader = null;
    if (!h) return;
    if (h.format === "jpeg") msPerPixel = h.render_ms / (h.width * h.height);
    const img = $("frame");
    const old = img.src;
    img.src = URL.createObjectURL(ev.data);
    if (old) URL.revokeObjectURL(old);
    const shot = asked.get(h.frame) || view;
    for (const id of asked.keys()) if (id <= h.frame) asked.delete(id);
    Object.assign(img.dataset, {
      frame: String(h.frame),
      step: String(h.step),
      rank: h.rank === null || h.rank === undefined ? "all" : String(h.rank),
      kind: h.format === "png" ? "still" : "interactive",
      angle: String(shot.angle),
      elevation: String(shot.elevation),
      zoom: String(shot.zoom),
      width: String(h.width),
      vdiResolution: String(h.vdi_resolution),
      tf: h.tf ? h.tf.hash : "",
    });
    $("frame-info").textContent =
      `step ${h.step} · ${h.format} ${h.width}² from r = ${h.vdi_resolution} · ` +
      `${(h.bytes / 1024).toFixed(1)} KiB · ` +
      `render ${h.render_ms.toFixed(1)} ms · encode ${h.encode_ms.toFixed(1)} ms`;
    shownHeader = h;
    drawOverlay();
    drawLegend(h.tf);
    if (shownStep !== h.step) {
      shownStep = h.step;
      showPanel();
    }
    if (fitPending && h.fit_zoom) {
      fitPending = false;
      if (Math.abs(h.fit_zoom - view.zoom) > 0.005 * view.zoom) {
        view.zoom = h.fit_zoom;
        request(false);
      }
    }
  };
}

// Where world point `p` lands in a `w × h` image seen by `cam` ({eye, target, up, fov_y_deg}),
// as the renderer casts its rays (core/src/camera.rs, ViewFrame::ray); null behind the eye.
function project(cam, p, w, h) {
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const unit = (a) => { const n = Math.hypot(...a) || 1; return a.map((v) => v / n); };
  const forward = unit(sub(cam.target, cam.eye));
  const right = unit(cross(forward, cam.up));
  const up = cross(right, forward);
  const e = sub(p, cam.eye);
  const z = dot(e, forward);
  if (!(z > 1e-6)) return null;
  const ty = Math.tan((cam.fov_y_deg * Math.PI) / 360);
  const tx = ty * (w / h);
  return [((dot(e, right) / z / tx + 1) / 2) * w, ((1 - dot(e, up) / z / ty) / 2) * h];
}

// The volume's bounding box over the frame, its three edges from the lower corner coloured
// as the axes (x red, y green, z blue) and labelled.
function drawOverlay() {
  const c = $("overlay");
  const img = $("frame");
  const [W, H] = [img.clientWidth, img.clientHeight];
  if (c.width !== W || c.height !== H) Object.assign(c, { width: W, height: H });
  const g = c.getContext("2d");
  g.clearRect(0, 0, W, H);
  const h = shownHeader;
  c.dataset.edges = "0";
  if (!$("show-box").checked || !h || !h.camera || !h.box) return;
  const { min, max } = h.box;
  const corner = (k) => [k & 1 ? max[0] : min[0], k & 2 ? max[1] : min[1], k & 4 ? max[2] : min[2]];
  // The image is square in a square element: pixels scale by W / width.
  const at = (k) => {
    const q = project(h.camera, corner(k), h.width, h.height);
    return q && [(q[0] * W) / h.width, (q[1] * H) / h.height];
  };
  // How far the box reaches towards the frame's edges (1: it touches one), for scripts and tests.
  const reach = [...Array(8).keys()].map(at).filter(Boolean)
    .map(([x, y]) => Math.max(Math.abs(x / W - 0.5), Math.abs(y / H - 0.5)) * 2);
  c.dataset.reach = reach.length === 8 ? Math.max(...reach).toFixed(3) : "";
  const axes = { 1: ["#e55", "x"], 2: ["#5c5", "y"], 4: ["#59f", "z"] };
  let drawn = 0;
  g.lineWidth = 1;
  for (let a = 0; a < 8; a++) {
    for (const bit of [1, 2, 4]) {
      if (a & bit) continue;
      const [p, q] = [at(a), at(a | bit)];
      if (!p || !q) continue;
      const axis = a === 0 ? axes[bit] : null;
      g.strokeStyle = axis ? axis[0] : "rgba(200, 200, 200, 0.55)";
      g.beginPath();
      g.moveTo(p[0], p[1]);
      g.lineTo(q[0], q[1]);
      g.stroke();
      if (axis) {
        g.fillStyle = axis[0];
        g.font = "12px monospace";
        g.fillText(axis[1], q[0] + 3, q[1] - 3);
      }
      drawn++;
    }
  }
  c.dataset.edges = String(drawn);
}

// The colour legend of the frame's transfer function: colour along its domain, opacity as the
// curve above, the domain's ends and the TF's name. `tf`: {name, hash} from the frame header.
async function drawLegend(tf) {
  $("legend").hidden = !$("show-legend").checked;
  if (!tf || tf.hash === legendHash) return;
  legendHash = tf.hash;
  $("legend-name").textContent = tf.name;
  const bar = $("legend-bar");
  const g = bar.getContext("2d");
  g.clearRect(0, 0, bar.width, bar.height);
  const r = await fetch(withToken(`api/tf?hash=${tf.hash}`)).catch(() => null);
  const body = r && r.ok ? await r.json() : null;
  if (!body || !body.tf) {
    $("legend-lo").textContent = "";
    $("legend-hi").textContent = "";
    $("legend-name").textContent = `${tf.name} (colours not held by this viewer)`;
    return;
  }
  const { domain, points } = body.tf;
  const at = (x) => {
    let i = 0;
    while (i < points.length - 1 && points[i + 1][0] < x) i++;
    const [a, b] = [points[i], points[Math.min(i + 1, points.length - 1)]];
    const t = b[0] > a[0] ? Math.max(0, Math.min(1, (x - a[0]) / (b[0] - a[0]))) : 0;
    return a.map((v, k) => v + (b[k] - v) * t);
  };
  const [w, hgt] = [bar.width, bar.height];
  const strip = Math.round(hgt / 2);
  g.strokeStyle = "#ddd";
  g.beginPath();
  for (let x = 0; x < w; x++) {
    const [, cr, cg, cb, ca] = at(x / (w - 1));
    g.fillStyle = `rgb(${cr * 255}, ${cg * 255}, ${cb * 255})`;
    g.fillRect(x, hgt - strip, 1, strip);
    const y = hgt - strip - 1 - ca * (hgt - strip - 2);
    if (x === 0) g.moveTo(x, y); else g.lineTo(x, y);
  }
  g.stroke();
  const fmt = (v) => Number(v).toPrecision(4);
  $("legend-lo").textContent = fmt(domain[0]);
  $("legend-hi").textContent = fmt(domain[1]);
  bar.dataset.hash = tf.hash;
}

async function getJson(path) {
  const r = await fetch(withToken(path));
  const body = await r.json();
  if (!r.ok) throw new Error(body.error || r.statusText);
  return body;
}

// Re-reads the steps and the series; follows the latest step when asked to.
let refreshing = false;
async function refresh() {
  if (refreshing) return;
  refreshing = true;
  try {
    const s = await getJson("api/steps");
    const before = steps.length;
    steps = s.steps;
    const slider = $("slider");
    slider.max = String(Math.max(0, steps.length - 1));
    if (steps.length > 0) {
      // The movie of the steps shown, orbiting from the elevation on screen (ffmpeg on the node).
      const range = `from=${steps[0].step}&to=${steps[steps.length - 1].step}`;
      $("movie").href = withToken(`api/movie?${range}&elevation=${Math.round(view.elevation)}`);
    }
    if (steps.length > 0) {
      // The movie of the steps shown, orbiting from the elevation on screen (ffmpeg on the node).
      const range = `from=${steps[0].step}&to=${steps[steps.length - 1].step}`;
      $("movie").href = withToken(`api/movie?${range}&elevation=${Math.round(view.elevation)}`);
    }
    if ($("follow").checked) slider.value = slider.max;
    updateRanks();
    series = await getJson("api/series");
    drawCharts();
    if ($("follow").checked && steps.length !== before) request(false);
    showPanel();
  } catch (e) {
    $("status").textContent = String(e.message || e);
  } finally {
    refreshing = false;
  }
}

function currentEntry() {
  const want = shownStep ?? (steps.length ? steps[steps.length - 1].step : null);
  return steps.find((s) => s.step === want);
}

function updateRanks() {
  const sel = $("rank");
  const world = Math.max(1, ...steps.map((s) => s.world_size));
  if (sel.options.length === world + 1) return;
  sel.length = 1;
  for (let r = 0; r < world; r++) sel.add(new Option(`rank ${r}`, String(r)));
}

const fmtQ = (q) => (q === null || q === undefined ? "–" : q === "inf" ? "∞" : Number(q).toFixed(2));

function showPanel() {
  const s = currentEntry();
  $("step-label").textContent = s ? `${s.step}` : "–";
  $("slider").dataset.step = s ? String(s.step) : "";
  if (!s) return;
  const q = s.quality;
  const rows = [
    ["step", s.step + (s.world_size > 1 ? ` (${s.ranks_held}/${s.world_size} ranks${s.partial ? ", partial" : ""}${s.error ? ", not composed" : ""})` : "")],
    ["P_M", `r ${s.r}, γ ${Number(s.gamma).toFixed(4)}`],
    ["P_M version", s.pm_version],
    ["σ", `${(s.sigma_bytes / 1000).toFixed(1)} kB`],
    ["τ", `${Number(s.tau_s).toFixed(3)} s`],
    ["q", q ? `${fmtQ(q.q_db)} dB` : "not sampled"],
  ];
  if (s.error) rows.push(["composition", s.error]);
  if (q) {
    rows.push(["q per view", q.view_q_db.map(fmtQ).join(", ")]);
    rows.push(["SSIM", q.ssim === null ? "–" : Number(q.ssim).toFixed(4)]);
  }
  const t = $("panel");
  t.replaceChildren(...rows.map(([k, v]) => {
    const tr = document.createElement("tr");
    const a = document.createElement("td");
    const b = document.createElement("td");
    a.textContent = k;
    b.textContent = String(v);
    tr.append(a, b);
    return tr;
  }));
  const tv = $("test-view");
  const views = q ? q.view_q_db.length : 0;
  if (tv.length !== views) {
    tv.length = 0;
    for (let k = 0; k < views; k++) tv.add(new Option(`test view ${k}`, String(k)));
  }
  $("compare").disabled = !s.sampled;
}

// One chart: a line over the stored steps, the budget as a horizontal line, P_M changes as
// vertical markers.
function chart(canvas, xs, ys, budget, changes) {
  const ctx = canvas.getContext("2d");
  const { width: w, height: h } = canvas;
  ctx.clearRect(0, 0, w, h);
  const pts = xs.map((x, i) => [x, ys[i] === "inf" ? null : ys[i]]).filter((p) => p[1] !== null && p[1] !== undefined);
  canvas.dataset.points = String(pts.length);
  if (pts.length === 0) return;
  const vals = pts.map((p) => p[1]).concat(budget !== null && budget !== undefined ? [budget] : []);
  let lo = Math.min(...vals), hi = Math.max(...vals);
  if (hi === lo) { hi += 1; lo -= 1; }
  const x0 = Math.min(...xs), x1 = Math.max(...xs);
  const px = (x) => 30 + ((x - x0) / Math.max(1e-9, x1 - x0)) * (w - 40);
  const py = (y) => h - 14 - ((y - lo) / (hi - lo)) * (h - 24);
  ctx.fillStyle = "#888";
  ctx.font = "10px monospace";
  ctx.fillText(hi.toPrecision(3), 0, 10);
  ctx.fillText(lo.toPrecision(3), 0, h - 14);
  ctx.strokeStyle = "#69f";
  for (const c of changes) {
    ctx.beginPath();
    ctx.moveTo(px(c.step), 0);
    ctx.lineTo(px(c.step), h);
    ctx.stroke();
  }
  if (budget !== null && budget !== undefined) {
    ctx.strokeStyle = "#e94";
    ctx.beginPath();
    ctx.moveTo(30, py(budget));
    ctx.lineTo(w, py(budget));
    ctx.stroke();
  }
  ctx.strokeStyle = "#ddd";
  ctx.fillStyle = "#ddd";
  ctx.beginPath();
  pts.forEach(([x, y], i) => (i ? ctx.lineTo(px(x), py(y)) : ctx.moveTo(px(x), py(y))));
  ctx.stroke();
  for (const [x, y] of pts) ctx.fillRect(px(x) - 1.5, py(y) - 1.5, 3, 3);
}

function drawCharts() {
  if (!series) return;
  const b = series.budget || {};
  chart($("chart-sigma"), series.step, series.sigma_bytes, b.sigma_bytes, series.pm_changes);
  chart($("chart-tau"), series.step, series.tau_s, b.tau_s, series.pm_changes);
  chart($("chart-q"), series.step, series.q_db, b.q_db, series.pm_changes);
  // Adherence of the steps made with a tuned P_M to the budget, under its chart.
  const a = series.adherence || {};
  for (const k of ["sigma", "tau"]) {
    const x = a[k];
    $(`adherence-${k}`).textContent = x
      ? `${x.within} of ${x.steps} tuned steps within the budget (${Math.round(100 * x.share)} %), worst ${x.worst_ratio.toFixed(2)}×`
      : "";
  }
}

// VDI vs reference: the stored reference frame of a test view beside the VDI at that view.
async function showComparison() {
  const on = $("compare").checked;
  $("reference").hidden = !on;
  $("test-view").hidden = !on;
  if (!on) return;
  const s = currentEntry();
  if (!s) return;
  const k = Number($("test-view").value || 0);
  const rank = selectedRank();
  const r = await fetch(withToken(`api/reference?step=${s.step}&view=${k}` + (rank === null ? "" : `&rank=${rank}`)));
  if (!r.ok) {
    $("status").textContent = (await r.json()).error;
    return;
  }
  const angle = Number(r.headers.get("x-angle"));
  $("reference").src = URL.createObjectURL(await r.blob());
  Object.assign(view, { angle, elevation: 0, zoom: 1 });
  $("follow").checked = false;
  $("slider").value = String(steps.findIndex((e) => e.step === s.step));
  request(false);
}

function wire() {
  const img = $("frame");
  let drag = null;
  img.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY, angle: view.angle, elevation: view.elevation };
    img.setPointerCapture(e.pointerId);
  });
  img.addEventListener("pointermove", (e) => {
    if (!drag) return;
    view.angle = drag.angle - (e.clientX - drag.x) * 0.5;
    view.elevation = Math.max(-89, Math.min(89, drag.elevation + (e.clientY - drag.y) * 0.5));
    request(true);
  });
  const end = () => { drag = null; };
  img.addEventListener("pointerup", end);
  img.addEventListener("pointercancel", end);
  img.addEventListener("wheel", (e) => {
    e.preventDefault();
    view.zoom = Math.max(0.05, Math.min(20, view.zoom * (e.deltaY > 0 ? 1.1 : 1 / 1.1)));
    request(true);
  }, { passive: false });
  $("reset").onclick = () => {
    Object.assign(view, { angle: 0, elevation: 0 });
    fitPending = true;
    request(false);
  };
  $("fit").onclick = () => {
    fitPending = true;
    request(false);
  };
  $("show-box").onchange = drawOverlay;
  $("show-legend").onchange = () => { $("legend").hidden = !$("show-legend").checked; };
  window.addEventListener("resize", drawOverlay);
  $("slider").oninput = () => {
    $("follow").checked = false;
    shownStep = steps[Number($("slider").value)]?.step ?? null;
    showPanel();
    request(true);
  };
  $("follow").onchange = () => {
    if ($("follow").checked) {
      $("slider").value = $("slider").max;
      request(false);
    }
  };
  $("rank").onchange = () => request(false);
  $("compare").onchange = showComparison;
  $("test-view").onchange = showComparison;
}

wire();
connect();
refresh();

// For scripts driving the page (and the browser test): drop the live socket as a network
// failure would; the page reconnects on its own and asks for the current camera again.
window.insituViewer = { dropConnection: () => socket && socket.close() };

// ---- Steering (docs/steering.md): the transfer function, the field, the generation camera
// and the budget, sent to `api/steer` with the steering token (typed here, sent as a header,
// never put into a URL). The panel shows only where the viz-node steers.

const tf = {
  map: null, // the colour map's name (api/colormaps)
  maps: {}, // name → colours sampled evenly over [0, 1]
  lo: 0,
  hi: 1,
  // Opacity control points [x in [0, 1], opacity per voxel], x ascending; the ends stay.
  points: [[0, 0], [0.5, 0.05], [1, 0.6]],
  histogram: null, // the newest step's {lo, hi, counts} (api/scene)
};
let tfDrag = null; // index of the point being dragged

function mapColour(x) {
  const c = tf.maps[tf.map] || [[0, 0, 0], [1, 1, 1]];
  const f = Math.max(0, Math.min(1, x)) * (c.length - 1);
  const i = Math.min(c.length - 2, Math.floor(f));
  const t = f - i;
  return c[i].map((v, k) => v + (c[i + 1][k] - v) * t);
}

function opacityAt(x) {
  const p = tf.points;
  for (let i = 1; i < p.length; i++) {
    if (x <= p[i][0]) {
      const t = p[i][0] > p[i - 1][0] ? (x - p[i - 1][0]) / (p[i][0] - p[i - 1][0]) : 0;
      return p[i - 1][1] + (p[i][1] - p[i - 1][1]) * t;
    }
  }
  return p[p.length - 1][1];
}

// The transfer function as the nodes take it: `[x, r, g, b, a]` points at every control point
// and at 17 even steps (the colours between follow the map).
function tfJson() {
  const xs = new Set(tf.points.map((p) => p[0]));
  for (let i = 0; i <= 16; i++) xs.add(i / 16);
  const points = [...xs].sort((a, b) => a - b).map((x) => {
    const [r, g, b] = mapColour(x);
    return [x, r, g, b, opacityAt(x)].map((v) => Math.round(v * 1e4) / 1e4);
  });
  return { domain: [tf.lo, tf.hi], points };
}

function drawTf() {
  const cv = $("tf-editor");
  const g = cv.getContext("2d");
  const { width: w, height: h } = cv;
  const strip = 14;
  g.clearRect(0, 0, w, h);
  for (let px = 0; px < w; px++) {
    const [r, gg, b] = mapColour(px / (w - 1));
    g.fillStyle = `rgb(${r * 255},${gg * 255},${b * 255})`;
    g.fillRect(px, h - strip, 1, strip);
  }
  const y = (a) => (h - strip - 6) * (1 - a) + 3;
  // The newest step's histogram under the curve (log counts), placed by value on the range.
  const hist = tf.histogram;
  if (hist && hist.hi > hist.lo && tf.hi > tf.lo) {
    const n = hist.counts.length;
    const top = Math.log1p(Math.max(...hist.counts)) || 1;
    g.fillStyle = "#3a3a3a";
    hist.counts.forEach((c, i) => {
      const v0 = hist.lo + ((hist.hi - hist.lo) * i) / n;
      const v1 = hist.lo + ((hist.hi - hist.lo) * (i + 1)) / n;
      const x0 = ((v0 - tf.lo) / (tf.hi - tf.lo)) * (w - 1);
      const x1 = ((v1 - tf.lo) / (tf.hi - tf.lo)) * (w - 1);
      const bar = (Math.log1p(c) / top) * (h - strip - 6);
      g.fillRect(x0, h - strip - bar, Math.max(1, x1 - x0), bar);
    });
  }
  cv.dataset.histogram = hist ? String(hist.counts.length) : "0";
  g.strokeStyle = "#eee";
  g.beginPath();
  tf.points.forEach(([x, a], i) => (i ? g.lineTo(x * (w - 1), y(a)) : g.moveTo(x * (w - 1), y(a))));
  g.stroke();
  g.fillStyle = "#e94";
  for (const [x, a] of tf.points) {
    g.beginPath();
    g.arc(x * (w - 1), y(a), 5, 0, 2 * Math.PI);
    g.fill();
  }
  cv.dataset.points = JSON.stringify(tf.points);
}

function tfPoint(e) {
  const cv = $("tf-editor");
  const r = cv.getBoundingClientRect();
  const x = Math.max(0, Math.min(1, (e.clientX - r.left) / r.width));
  const strip = 14 * (r.height / cv.height);
  const a = Math.max(0, Math.min(1, 1 - (e.clientY - r.top - 3) / (r.height - strip - 6)));
  return [x, a];
}

function nearestPoint(x, a) {
  let best = -1;
  let bestD = 0.05;
  tf.points.forEach(([px, pa], i) => {
    const d = Math.hypot(px - x, (pa - a) * 0.5);
    if (d < bestD) [best, bestD] = [i, d];
  });
  return best;
}

function steerStatus(text, error) {
  const el = $("steer-status");
  el.textContent = text;
  el.className = error ? "legend error" : "legend";
}

function steerPost(path, body) {
  const token = $("steer-token").value.trim();
  return fetch(withToken(path), {
    method: "POST",
    headers: { "content-type": "application/json", ...(token ? { authorization: `Bearer ${token}` } : {}) },
    body: JSON.stringify(body),
  });
}

/** The view on screen as the steering API takes a camera. */
function shownView() {
  return { step: shownStep, angle: view.angle, elevation: view.elevation, zoom: view.zoom };
}

/** The edited transfer function rendered on the newest held step by the nodes, not applied. */
async function previewTf() {
  if (!(tf.hi > tf.lo)) return steerStatus("the range's upper end must exceed its lower", true);
  const r = await steerPost("api/preview", { tf: tfJson(), camera: shownView(), size: 256 });
  if (!r.ok) {
    const reply = await r.json().catch(() => ({ error: `HTTP ${r.status}` }));
    return steerStatus(`no preview: ${reply.error}`, true);
  }
  const img = $("tf-preview-image");
  URL.revokeObjectURL(img.src);
  img.src = URL.createObjectURL(await r.blob());
  await img.decode().catch(() => {});
  const h = (k) => r.headers.get(`x-insitu-${k}`);
  $("tf-preview-caption").textContent =
    `preview: step ${h("step")}, ${h("ranks")} rank(s), rendered in ${Number(h("render-secs")).toFixed(2)} s`;
  const fig = $("tf-preview-figure");
  fig.hidden = false;
  fig.dataset.step = h("step");
  steerStatus("previewed; not applied", false);
}

async function steer(body) {
  const r = await steerPost("api/steer", body);
  const reply = await r.json().catch(() => ({ error: `HTTP ${r.status}` }));
  if (!r.ok) {
    steerStatus(`refused: ${reply.error}`, true);
    return null;
  }
  steerStatus(
    reply.pm_version
      ? `scene ${reply.scene_version} from step ${reply.from_step} (decision ${reply.pm_version})` +
        (reply.superseded.length ? `; superseded ${reply.superseded.join(", ")}` : "")
      : `utility ${reply.utility}`,
    false,
  );
  $("steer").dataset.reply = JSON.stringify(reply);
  loadScene();
  return reply;
}

async function loadScene() {
  const s = await getJson("api/scene").catch(() => null);
  if (!s || !s.steering) return;
  $("steer").hidden = false;
  const sc = s.scene;
  $("steer-scene").textContent =
    `scene ${sc.version}` + (sc.tf_name ? `, ${sc.tf_name}` : "") + (sc.field ? `, field ${sc.field}` : "") +
    (sc.sample_distance != null ? `, sample distance ${sc.sample_distance}` : "") + (sc.shading ? ", shaded" : "") +
    `; ${s.utility}`;
  const field = $("steer-field");
  const names = s.fields || [];
  if (field.options.length !== names.length) {
    field.replaceChildren(...names.map((n) => new Option(n, n)));
  }
  if (sc.field) field.value = sc.field;
  if (sc.sample_distance != null && document.activeElement !== $("steer-sample-distance")) {
    $("steer-sample-distance").value = sc.sample_distance;
  }
  if (sc.shading != null) $("steer-shading").checked = sc.shading;
  if (s.histogram) {
    tf.histogram = s.histogram;
    drawTf();
  }
  field.disabled = names.length === 0;
  $("field-apply").disabled = names.length === 0;
}

async function wireSteering() {
  const maps = await getJson("api/colormaps").catch(() => null);
  if (maps) {
    tf.maps = maps;
    $("tf-map").replaceChildren(...Object.keys(maps).map((n) => new Option(n, n)));
    tf.map = maps.viridis ? "viridis" : Object.keys(maps)[0];
    $("tf-map").value = tf.map;
  }
  const s = await getJson("api/scene").catch(() => null);
  const domain = s?.scene?.tf?.domain || s?.configured_tf?.domain;
  if (domain) [tf.lo, tf.hi] = domain;
  $("tf-lo").value = Number(tf.lo.toPrecision(4));
  $("tf-hi").value = Number(tf.hi.toPrecision(4));
  $("tf-map").onchange = () => { tf.map = $("tf-map").value; drawTf(); };
  $("tf-lo").onchange = () => { tf.lo = Number($("tf-lo").value); drawTf(); };
  $("tf-hi").onchange = () => { tf.hi = Number($("tf-hi").value); drawTf(); };
  const cv = $("tf-editor");
  cv.addEventListener("pointerdown", (e) => {
    const [x, a] = tfPoint(e);
    const i = nearestPoint(x, a);
    if (e.shiftKey) {
      if (i > 0 && i < tf.points.length - 1) tf.points.splice(i, 1);
      drawTf();
      return;
    }
    if (i >= 0) {
      tfDrag = i;
      cv.setPointerCapture(e.pointerId);
    }
  });
  cv.addEventListener("pointermove", (e) => {
    if (tfDrag === null) return;
    const [x, a] = tfPoint(e);
    const p = tf.points;
    const last = p.length - 1;
    // The ends keep their x; the others stay between their neighbours.
    const px = tfDrag === 0 ? 0 : tfDrag === last ? 1 : Math.min(p[tfDrag + 1][0] - 1e-3, Math.max(p[tfDrag - 1][0] + 1e-3, x));
    p[tfDrag] = [px, a];
    drawTf();
  });
  const end = () => { tfDrag = null; };
  cv.addEventListener("pointerup", end);
  cv.addEventListener("pointercancel", end);
  cv.addEventListener("dblclick", (e) => {
    const [x, a] = tfPoint(e);
    if (nearestPoint(x, a) >= 0) return;
    tf.points.push([x, a]);
    tf.points.sort((p, q) => p[0] - q[0]);
    drawTf();
  });
  $("tf-apply").onclick = () => {
    if (!(tf.hi > tf.lo)) return steerStatus("the range's upper end must exceed its lower", true);
    return steer({ tf: tfJson(), tf_name: `${tf.map} (steered)` });
  };
  $("field-apply").onclick = () => steer({ field: $("steer-field").value });
  $("tf-preview").onclick = previewTf;
  $("generate-here").onclick = () => steer({ camera: shownView() });
  $("utility-apply").onclick = () => steer({ utility: $("steer-utility").value.trim() });
  $("sampling-apply").onclick = () => {
    const body = { shading: $("steer-shading").checked };
    const distance = $("steer-sample-distance").value.trim();
    if (distance !== "") body.sample_distance = Number(distance);
    return steer(body);
  };
  drawTf();
  loadScene();
}

wireSteering();
