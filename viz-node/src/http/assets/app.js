// The insitu web viewer: frames over a WebSocket (JPEG while dragging, PNG once the mouse
// rests), the stored steps and their series from the JSON API. No dependencies.

const token = new URLSearchParams(location.search).get("token");
const withToken = (path) =>
  token ? path + (path.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(token) : path;
const $ = (id) => document.getElementById(id);

const STILL_DELAY_MS = 300; // the still frame follows this long after the last camera change
const view = { angle: 0, elevation: 0, zoom: 1 };
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

// Asks for a frame: interactive (JPEG, at most ¼ area, see `interactiveSide`, from the VDI
// level that matches its size) or still (full PNG from the full VDI).
function request(interactive) {
  if (!socket || socket.readyState !== WebSocket.OPEN) return;
  const full = side();
  const px = interactive ? interactiveSide(full) : full;
  socket.send(JSON.stringify({
    id: nextId++,
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
    Object.assign(img.dataset, {
      frame: String(h.frame),
      step: String(h.step),
      rank: h.rank === null || h.rank === undefined ? "all" : String(h.rank),
      kind: h.format === "png" ? "still" : "interactive",
      angle: String(view.angle),
      elevation: String(view.elevation),
      zoom: String(view.zoom),
      width: String(h.width),
      vdiResolution: String(h.vdi_resolution),
    });
    $("frame-info").textContent =
      `step ${h.step} · ${h.format} ${h.width}² from r = ${h.vdi_resolution} · ` +
      `${(h.bytes / 1024).toFixed(1)} KiB · ` +
      `render ${h.render_ms.toFixed(1)} ms · encode ${h.encode_ms.toFixed(1)} ms`;
    if (shownStep !== h.step) {
      shownStep = h.step;
      showPanel();
    }
  };
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
    ["step", s.step + (s.world_size > 1 ? ` (${s.ranks.length}/${s.world_size} ranks${s.partial ? ", partial" : ""})` : "")],
    ["P_M", `r ${s.r}, γ ${Number(s.gamma).toFixed(4)}`],
    ["P_M version", s.pm_version],
    ["σ", `${(s.sigma_bytes / 1000).toFixed(1)} kB`],
    ["τ", `${Number(s.tau_s).toFixed(3)} s`],
    ["q", q ? `${fmtQ(q.q_db)} dB` : "not sampled"],
  ];
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
    Object.assign(view, { angle: 0, elevation: 0, zoom: 1 });
    request(false);
  };
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
