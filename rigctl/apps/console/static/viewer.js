// The run viewer: one record (`/records/RUN/data.json`, rigctl.apps.console.records) on one
// timeline. Scrubbing or playing (0.25-8x) sets one instant `t` (s since the run started, the
// record's clock) and everything shows that instant: the video frame whose time is nearest t
// (its index from the record's frame-time table, the frame fetched by index: the record's
// Motion-JPEG is no <video> a browser plays, see records.py), the plan and the tracked agents over
// it (or the scene drawn from the tracked positions when the record has no video, or the arms
// from their recorded joints on an arms rig), the move, the events so far and a cursor on every
// channel plot (plots.js's TimePlot over the whole run).
// `window.rigctlViewer` exposes what the page shows (for the browser tests and bench/viewer.py).
"use strict";

const $ = (id) => document.getElementById(id);
const AGENT_COLORS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#17becf"];
const SPEEDS = [0.25, 0.5, 1, 2, 4, 8];

const V = window.rigctlViewer = {
  run: new URLSearchParams(location.search).get("run"),
  data: null, t: 0, playing: false, speed: 1, ready: false, error: null,
  scene: null, wantedFrame: null, shownFrame: null, agentsMm: null, move: null, plots: [],
};

// a console beyond loopback wants its token (docs/console.md): from the link's #token=, kept for
// this tab only, sent with every request for the record (never in a URL the server sees)
(function takeToken() {
  const fromHash = new URLSearchParams(location.hash.slice(1)).get("token");
  if (fromHash) {
    sessionStorage.setItem("rigctl-token", fromHash);
    history.replaceState(null, "", location.pathname + location.search);
  }
})();
function api(path) {
  const token = sessionStorage.getItem("rigctl-token");
  return fetch(path, token ? { headers: { Authorization: `Bearer ${token}` } } : {});
}

// -- helpers --------------------------------------------------------------------------------------
function nearestIndex(times, t) {
  // the index of the time in the sorted `times` nearest `t` (the earlier one on a tie)
  let lo = 0, hi = times.length;
  while (lo < hi) { const mid = (lo + hi) >> 1; if (times[mid] < t) lo = mid + 1; else hi = mid; }
  if (lo === 0) return 0;
  if (lo === times.length) return times.length - 1;
  return t - times[lo - 1] <= times[lo] - t ? lo - 1 : lo;
}
function lastAtOrBefore(times, t) {
  let lo = 0, hi = times.length;
  while (lo < hi) { const mid = (lo + hi) >> 1; if (times[mid] <= t) lo = mid + 1; else hi = mid; }
  return lo - 1;
}
const fmt = (v, d = 1) => (v == null || !isFinite(v) ? "-" : v.toFixed(d));
function message(text) { const m = $("message"); m.hidden = !text; m.textContent = text || ""; }

// -- loading ---------------------------------------------------------------------------------------
async function listRecords() {
  let runs;
  try { const r = await api("/records"); if (!r.ok) return; runs = await r.json(); } catch { return; }
  const choice = $("run-choice");
  for (const run of runs) {
    const o = document.createElement("option");
    o.value = run.id;
    o.textContent = `${run.id}${run.plan ? ` (${run.plan})` : ""}${run.video ? "" : ", no video"}`;
    if (run.id === V.run) o.selected = true;
    choice.append(o);
  }
  choice.addEventListener("change", () => { if (choice.value) location.search = `?run=${encodeURIComponent(choice.value)}`; });
}

async function load() {
  listRecords();
  if (!V.run) { message("no record chosen: pick one above (or open /viewer?run=RUN_ID)"); V.error = "no run"; return; }
  let r;
  try { r = await api(`/records/${encodeURIComponent(V.run)}/data.json`); } catch (err) { V.error = String(err); message(`cannot reach the viewer: ${err}`); return; }
  if (!r.ok) { V.error = await r.text(); message(V.error); return; }
  V.data = await r.json();
  setUp(V.data);
  seek(V.data.t_start_s);
  V.ready = true;
}

function setUp(d) {
  $("run-name").textContent = `${d.id}${d.plan ? `: ${d.plan}` : ""}${d.rig ? ` (${d.rig})` : ""}`;
  document.title = `${d.id}: rigctl run viewer`;
  const verdict = $("verdict");
  const faults = d.events.some((e) => e.event === "fault" || e.event === "estop");
  verdict.textContent = !d.finished ? "unfinished" : faults ? "fault" : d.reached ? "reached" : d.reached === false ? "missed" : "finished";
  verdict.className = `verdict ${verdict.textContent}`;
  V.scene = d.scene.kind;
  const video = d.video && d.scene.kind === "camera";
  $("stage").classList.toggle("over-video", video);
  $("stage").classList.toggle("wide", d.scene.kind !== "camera");
  if (d.scene.kind !== "camera") { const c = $("scene"); c.width = 760; c.height = d.scene.kind === "arms" ? 380 : 420; }
  $("agents").hidden = !d.agents;
  $("frame").hidden = !video;
  $("scene-title").textContent = { camera: "Camera (the recorded video)", drawn: "Scene (drawn: no video)", arms: "Arms (top and side views)" }[d.scene.kind];
  $("legend").textContent = d.scene.kind === "arms"
    ? `grey: arm links (joint origins); red: EPMs; dashed: keep-out sphere. Scene: ${d.scene.why}.`
    : `dashed: planned path; x: goal; ring: expected after the current move; line: tracked path so far; disc: tracked now. Scene: ${d.scene.why}.`;
  if (d.scene.kind === "camera" && d.scene.resolution) {
    const c = $("scene"); [c.width, c.height] = d.scene.resolution;
  }
  if (!d.video) $("frame-info").textContent = "no video in this record";
  // the timeline
  const scrub = $("scrub");
  scrub.min = d.t_start_s; scrub.max = d.t_end_s;
  scrub.addEventListener("input", () => seek(parseFloat(scrub.value)));
  $("play").addEventListener("click", () => (V.playing ? pause() : play()));
  $("speed").addEventListener("change", () => { V.speed = parseFloat($("speed").value); });
  document.addEventListener("keydown", (e) => {
    if (e.target.tagName === "SELECT") return;
    if (e.key === " ") { e.preventDefault(); V.playing ? pause() : play(); }
    const step = d.video ? frameStep(e.key) : null;
    if (step != null) { e.preventDefault(); seek(step); }
  });
  // the events
  const list = $("events");
  d.events.forEach((e, i) => {
    const li = document.createElement("li");
    const t = document.createElement("span"); t.className = "t"; t.textContent = `${fmt(e.t, 2)} s`;
    li.append(t, ` ${e.event}${describe(e)}`);
    if (e.event === "fault" || e.event === "estop") li.classList.add("fault");
    li.dataset.index = i;
    li.addEventListener("click", () => { pause(); seek(e.t); });
    list.append(li);
  });
  // the channels: one plot per group and unit, over the whole run, a cursor canvas on each
  const plots = $("plots");
  if (!d.plots.length) plots.textContent = "no channels streamed in this record";
  for (const p of d.plots) {
    const h = document.createElement("h2"); h.textContent = `${p.title}, measured`;
    const wrap = document.createElement("div"); wrap.className = "plot";
    const canvas = document.createElement("canvas"); canvas.width = 1200; canvas.height = p.channels.length > 8 ? 260 : 190;
    canvas.setAttribute("aria-label", p.title);
    const cursor = document.createElement("canvas"); cursor.className = "cursor"; cursor.width = canvas.width; cursor.height = canvas.height;
    wrap.append(canvas, cursor);
    plots.append(h, wrap);
    const plot = new TimePlot(canvas, { yLabel: p.y_label, range: [d.t_start_s, d.t_end_s], maxPoints: 1e9, xLabel: "time since the run started (s)" });
    for (const c of p.channels) {
      const { t, y } = c.measured;
      for (let i = 0; i < t.length; i++) plot.add(c.name, t[i], y[i] == null ? NaN : y[i]);
    }
    const lows = new Set(p.channels.map((c) => c.low)), highs = new Set(p.channels.map((c) => c.high));
    if (lows.size === 1 && highs.size === 1) {
      const [low] = lows, [high] = highs, limits = [];
      if (low != null && isFinite(low)) limits.push({ y: low, label: `limit ${formatTick(low)} ${p.unit}` });
      if (high != null && isFinite(high)) limits.push({ y: high, label: `limit ${formatTick(high)} ${p.unit}` });
      plot.setLimits(limits);
    }
    plot.draw();
    wrap.addEventListener("click", (e) => {  // click a plot: go to that time
      const b = plot.box, r = canvas.getBoundingClientRect();
      const x = (e.clientX - r.left) * canvas.width / r.width;
      if (b && x >= b.left && x <= b.right) { pause(); seek(b.tMin + (x - b.left) / (b.right - b.left) * b.span); }
    });
    V.plots.push({ plot, cursor });
  }
}

function describe(e) {
  const skip = new Set(["t", "event"]);
  const parts = [];
  for (const [k, v] of Object.entries(e)) {
    if (skip.has(k) || v == null || typeof v === "object") continue;
    parts.push(`${k}=${typeof v === "number" ? +v.toFixed(4) : v}`);
    if (parts.length >= 4) break;
  }
  return parts.length ? `: ${parts.join(", ")}` : "";
}

function frameStep(key) {
  const times = V.data.video.t_s, k = nearestIndex(times, V.t);
  if (key === "ArrowRight") return times[Math.min(times.length - 1, k + 1)];
  if (key === "ArrowLeft") return times[Math.max(0, k - 1)];
  return null;
}

// -- the instant -----------------------------------------------------------------------------------
function seek(t) {
  const d = V.data;
  V.t = Math.min(d.t_end_s, Math.max(d.t_start_s, t));
  if (Math.abs(parseFloat($("scrub").value) - V.t) > 1e-9) $("scrub").value = V.t;
  $("clock").textContent = `t = ${V.t.toFixed(2)} s`;
  $("time-label").textContent = `${V.t.toFixed(2)} s of ${d.t_end_s.toFixed(2)} s`;
  // the move streamed at t (-1 between moves)
  const m = lastAtOrBefore(d.moves.map((x) => x[0]), V.t);
  V.move = m >= 0 ? d.moves[m][1] : -1;
  const done = d.moves.filter((x) => x[0] <= V.t && x[1] >= 0).reduce((a, x) => Math.max(a, x[1]), -1);
  $("move").textContent = !d.moves.length ? "no stream in this record" : V.move >= 0 ? `${V.move + 1} of ${d.n_moves || "?"}` : done < 0 ? "before the first move" : `between moves (${done + 1} of ${d.n_moves || "?"} done)`;
  agentsAt(V.t);
  if (d.video && d.video.frames) showFrame(nearestIndex(d.video.t_s, V.t));
  drawScene();
  for (const { plot, cursor } of V.plots) drawCursor(plot, cursor);
  markEvents();
}

function agentsAt(t) {
  // where the tracker had each agent at t: between two pictures, in between (as `rigctl report --video`)
  const a = V.data.agents;
  V.agentsMm = null; V.agentsScene = null;
  if (!a || !a.t.length) return;
  const k = lastAtOrBefore(a.t, t);
  if (k < 0) return;
  const at = (rows) => {
    if (k === a.t.length - 1 || a.t[k] === t) return rows[k].map((v) => (v == null ? NaN : v));
    const f = (t - a.t[k]) / (a.t[k + 1] - a.t[k]);
    return rows[k].map((v, j) => (v == null || rows[k + 1][j] == null ? NaN : v + f * (rows[k + 1][j] - v)));
  };
  const pairs = (flat) => Array.from({ length: a.n }, (_, i) => [flat[2 * i], flat[2 * i + 1]]);
  V.agentsMm = pairs(at(a.mm));
  if (a.scene) V.agentsScene = pairs(at(a.scene));
  V.trackedUpTo = k;
  const body = $("agents").tBodies[0];
  body.textContent = "";
  V.agentsMm.forEach(([x, y], i) => {
    const tr = body.insertRow();
    const name = tr.insertCell(); name.textContent = `#${i}`; name.style.color = AGENT_COLORS[i % AGENT_COLORS.length];
    tr.insertCell().textContent = isFinite(x) ? `${fmt(x)}, ${fmt(y)}` : "lost";
    const goal = goalMm(i);
    tr.insertCell().textContent = goal && isFinite(x) ? fmt(Math.hypot(x - goal[0], y - goal[1])) : "-";
  });
}

function goalMm(i) { return (V.data.scene.goals_mm || [])[i] || null; }

async function showFrame(k) {
  // the newest wish wins: one fetch in flight, then the latest frame asked meanwhile
  V.wantedFrame = k;
  if (V.fetching) return;
  V.fetching = true;
  try {
    while (V.shownFrame !== V.wantedFrame) {
      const want = V.wantedFrame, img = $("frame");
      const r = await api(`/records/${encodeURIComponent(V.run)}/frames/${want}.jpg`);
      if (!r.ok) { $("frame-info").textContent = `frame ${want}: ${r.status}`; break; }
      const url = URL.createObjectURL(await r.blob());
      const old = img.src;
      img.src = url;
      try { await img.decode(); } catch { /* shown when it loads */ }
      if (old.startsWith("blob:")) URL.revokeObjectURL(old);
      V.shownFrame = want;
      const c = $("scene");  // the video's pixels are the camera's (padded to even sides)
      if (img.naturalWidth && (c.width !== img.naturalWidth || c.height !== img.naturalHeight)) {
        [c.width, c.height] = [img.naturalWidth, img.naturalHeight]; drawScene();
      }
      const tf = V.data.video.t_s[want];
      $("frame-info").textContent = `frame ${want + 1} of ${V.data.video.frames}, taken at ${tf.toFixed(3)} s`;
    }
  } finally { V.fetching = false; }
}

function drawCursor(plot, cursor) {
  const ctx = cursor.getContext("2d"), b = plot.box;
  ctx.clearRect(0, 0, cursor.width, cursor.height);
  if (!b) return;
  const x = b.left + (V.t - b.tMin) / b.span * (b.right - b.left);
  ctx.strokeStyle = "#111"; ctx.lineWidth = 2;
  ctx.beginPath(); ctx.moveTo(x, b.top); ctx.lineTo(x, b.bottom); ctx.stroke();
}

function markEvents() {
  const events = V.data.events, k = lastAtOrBefore(events.map((e) => e.t), V.t);
  const list = $("events");
  for (const li of list.children) {
    const i = +li.dataset.index;
    li.classList.toggle("past", i <= k); li.classList.toggle("future", i > k); li.classList.toggle("current", i === k);
  }
  if (k >= 0 && k !== V.currentEvent) {
    V.currentEvent = k;
    const li = list.children[k], top = li.offsetTop - list.offsetTop;
    if (top < list.scrollTop || top > list.scrollTop + list.clientHeight - li.offsetHeight) list.scrollTop = top - list.clientHeight / 2;
  }
}

// -- playing -----------------------------------------------------------------------------------------
function play() {
  if (V.t >= V.data.t_end_s) seek(V.data.t_start_s);
  V.playing = true; $("play").textContent = "pause";
  let last = performance.now();
  const tick = (now) => {
    if (!V.playing) return;
    seek(V.t + (now - last) / 1000 * V.speed);
    last = now;
    if (V.t >= V.data.t_end_s) { pause(); return; }
    requestAnimationFrame(tick);
  };
  requestAnimationFrame(tick);
}
function pause() { V.playing = false; $("play").textContent = "play"; }

// -- the scene -------------------------------------------------------------------------------------
function drawScene() {
  const kind = V.data.scene.kind;
  if (kind === "arms") return drawArmsAt(V.t);
  const canvas = $("scene"), ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  let map;
  if (kind === "camera") {
    map = ([x, y]) => [x, y];  // the canvas has the camera's pixels
  } else {
    map = drawnMap(canvas);
    ctx.fillStyle = "#fff"; ctx.fillRect(0, 0, canvas.width, canvas.height);
  }
  overlays(ctx, map, kind === "drawn");
  if (kind === "drawn") scaleBar(ctx, canvas);
}

function drawnMap(canvas) {
  // mm to canvas px, y up, everything the record draws inside with a margin (computed once)
  if (!V.drawn) {
    const s = V.data.scene, pts = [...s.boundary, ...s.obstacles.flat(), ...s.paths.flat(), ...s.goals];
    const a = V.data.agents;
    if (a && a.scene) for (const row of a.scene) for (let i = 0; i + 1 < row.length; i += 2) if (row[i] != null) pts.push([row[i], row[i + 1]]);
    const xs = pts.map((p) => p[0]), ys = pts.map((p) => p[1]);
    let x0 = Math.min(...xs), x1 = Math.max(...xs), y0 = Math.min(...ys), y1 = Math.max(...ys);
    if (!pts.length) { x0 = -50; x1 = 50; y0 = -50; y1 = 50; }
    const pad = 0.05 * Math.max(x1 - x0, y1 - y0, 10);
    x0 -= pad; x1 += pad; y0 -= pad; y1 += pad;
    const scale = Math.min(canvas.width / (x1 - x0), (canvas.height - 24) / (y1 - y0));
    const ox = (canvas.width - scale * (x1 - x0)) / 2, oy = (canvas.height - 24 - scale * (y1 - y0)) / 2;
    V.drawn = { scale, f: ([x, y]) => [ox + (x - x0) * scale, oy + (y1 - y) * scale] };
  }
  return V.drawn.f;
}

function scaleBar(ctx, canvas) {
  const s = V.drawn.scale, mm = niceTicks(0, canvas.width / s / 5, 2)[1] || 10;
  const x = 12, y = canvas.height - 10;
  ctx.strokeStyle = "#1b1d21"; ctx.lineWidth = 2; ctx.setLineDash([]);
  ctx.beginPath(); ctx.moveTo(x, y); ctx.lineTo(x + mm * s, y); ctx.moveTo(x, y - 4); ctx.lineTo(x, y + 4); ctx.moveTo(x + mm * s, y - 4); ctx.lineTo(x + mm * s, y + 4); ctx.stroke();
  ctx.fillStyle = "#1b1d21"; ctx.font = "13px system-ui, sans-serif"; ctx.textAlign = "left"; ctx.textBaseline = "bottom";
  ctx.fillText(`${formatTick(mm)} mm (floor, y up)`, x + mm * s + 8, y + 5);
}

function overlays(ctx, map, drawn) {
  const s = V.data.scene, a = V.data.agents;
  // canvas px per screen px: lines and labels keep their size on screen however the picture is scaled
  const u = Math.max(1, ctx.canvas.width / Math.max(1, ctx.canvas.clientWidth));
  const line = (pts, close) => { ctx.beginPath(); pts.forEach((p, i) => { const [x, y] = map(p); i ? ctx.lineTo(x, y) : ctx.moveTo(x, y); }); if (close) ctx.closePath(); };
  const ink = drawn ? "#39414d" : "rgba(255,255,255,.85)";
  ctx.lineWidth = 2 * u; ctx.setLineDash([]);
  if (s.boundary.length) { ctx.strokeStyle = ink; line(s.boundary, true); ctx.stroke(); }
  ctx.fillStyle = drawn ? "#c8cbd0" : "rgba(160,160,170,.35)"; ctx.strokeStyle = drawn ? "#5b6675" : "rgba(200,200,210,.8)";
  for (const o of s.obstacles) { line(o, true); ctx.fill(); ctx.stroke(); }
  const radius = (i) => {
    const r = a && a.radii_scene && a.radii_scene[i];
    return Math.max(4, drawn ? (r || 1) * V.drawn.scale : (r || 6));
  };
  s.paths.forEach((path, i) => {
    const colour = AGENT_COLORS[i % AGENT_COLORS.length];
    ctx.strokeStyle = colour; ctx.lineWidth = 2 * u; ctx.setLineDash([6 * u, 5 * u]); line(path); ctx.stroke(); ctx.setLineDash([]);
    if (V.move >= 0 && V.move + 1 < path.length) {  // where the plan expects it after this move
      const [x, y] = map(path[V.move + 1]);
      ctx.beginPath(); ctx.arc(x, y, radius(i) + 4 * u, 0, 2 * Math.PI); ctx.stroke();
    }
  });
  s.goals.forEach((g, i) => {
    const [x, y] = map(g), r = 7 * u;
    ctx.strokeStyle = AGENT_COLORS[i % AGENT_COLORS.length]; ctx.lineWidth = 3 * u;
    ctx.beginPath(); ctx.moveTo(x - r, y - r); ctx.lineTo(x + r, y + r); ctx.moveTo(x + r, y - r); ctx.lineTo(x - r, y + r); ctx.stroke();
  });
  if (!a || !a.scene || V.trackedUpTo == null || V.trackedUpTo < 0 || !V.agentsScene) return;
  for (let i = 0; i < a.n; i++) {
    const colour = AGENT_COLORS[i % AGENT_COLORS.length];
    const trail = [];
    for (let k = 0; k <= V.trackedUpTo; k++) if (a.scene[k][2 * i] != null) trail.push([a.scene[k][2 * i], a.scene[k][2 * i + 1]]);
    const [nx, ny] = V.agentsScene[i];
    if (isFinite(nx)) trail.push([nx, ny]);
    ctx.strokeStyle = colour; ctx.lineWidth = 2 * u;
    if (trail.length > 1) { line(trail); ctx.stroke(); }
    if (!isFinite(nx)) continue;
    const [x, y] = map([nx, ny]);
    ctx.globalAlpha = drawn ? 0.9 : 0.55; ctx.fillStyle = colour;
    ctx.beginPath(); ctx.arc(x, y, radius(i), 0, 2 * Math.PI); ctx.fill(); ctx.globalAlpha = 1;
    ctx.strokeStyle = drawn ? "#1b1d21" : colour; ctx.stroke();
    ctx.fillStyle = drawn ? "#1b1d21" : "#fff"; ctx.font = `bold ${Math.round(14 * u)}px system-ui, sans-serif`; ctx.textAlign = "left"; ctx.textBaseline = "alphabetic";
    ctx.fillText(`#${i}`, x + radius(i) + 3, y - radius(i));
  }
}

// -- the arms (the live console's views, from the recorded joints) ------------------------------------
function drawArmsAt(t) {
  const arms = V.data.arms, k = nearestIndex(arms.t, t);
  const msg = { arms: arms.frames[k], keep_out_mm: arms.keep_out_mm, epm_radius_mm: arms.epm_radius_mm };
  V.armsShown = k;
  const canvas = $("scene"), ctx = canvas.getContext("2d");
  const W = canvas.width, H = canvas.height;
  ctx.clearRect(0, 0, W, H);
  const views = [{ title: "top view", a: 0, b: 1, xl: "x (mm)", yl: "y (mm)" }, { title: "side view", a: 0, b: 2, xl: "x (mm)", yl: "z (mm)" }];
  if (!V.armsBox) {  // one scale for the whole run: the arms move, the axes do not
    const pts = arms.frames.flatMap((f) => f.flatMap((arm) => arm.points_mm));
    V.armsBox = views.map((v) => {
      const xs = pts.map((p) => p[v.a]).concat([-msg.keep_out_mm, msg.keep_out_mm]);
      const ys = pts.map((p) => p[v.b]).concat([-msg.keep_out_mm, msg.keep_out_mm]);
      return { lo: [Math.min(...xs), Math.min(...ys)], hi: [Math.max(...xs), Math.max(...ys)] };
    });
  }
  views.forEach((v, n) => {
    const left = n * W / 2 + 62, right = (n + 1) * W / 2 - 14, top = 26, bottom = H - 44;
    const { lo, hi } = V.armsBox[n];
    const span = Math.max(hi[0] - lo[0], hi[1] - lo[1]) * 1.1 + 1;
    const cx = (lo[0] + hi[0]) / 2, cy = (lo[1] + hi[1]) / 2;
    const scale = Math.min(right - left, bottom - top) / span;
    const ox = (left + right) / 2, oy = (top + bottom) / 2;
    const X = (x) => ox + (x - cx) * scale, Y = (y) => oy - (y - cy) * scale;
    ctx.strokeStyle = "#9aa1ab"; ctx.lineWidth = 1; ctx.strokeRect(left, top, right - left, bottom - top);
    ctx.fillStyle = "#39414d"; ctx.font = "13px system-ui, sans-serif"; ctx.textAlign = "center"; ctx.textBaseline = "alphabetic";
    ctx.fillText(v.title, (left + right) / 2, 16);
    ctx.fillText(v.xl, (left + right) / 2, H - 8);
    for (const x of niceTicks(cx - (right - left) / 2 / scale, cx + (right - left) / 2 / scale, 4)) if (X(x) >= left && X(x) <= right) ctx.fillText(formatTick(x), X(x), bottom + 16);
    ctx.textAlign = "right"; ctx.textBaseline = "middle";
    for (const y of niceTicks(cy - (bottom - top) / 2 / scale, cy + (bottom - top) / 2 / scale, 4)) if (Y(y) >= top && Y(y) <= bottom) ctx.fillText(formatTick(y), left - 4, Y(y));
    ctx.save(); ctx.translate(n * W / 2 + 14, (top + bottom) / 2); ctx.rotate(-Math.PI / 2); ctx.textAlign = "center"; ctx.fillText(v.yl, 0, 0); ctx.restore();
    ctx.textBaseline = "alphabetic";
    ctx.save(); ctx.beginPath(); ctx.rect(left, top, right - left, bottom - top); ctx.clip();
    ctx.setLineDash([5, 4]); ctx.strokeStyle = "#c0262d"; ctx.lineWidth = 1;
    ctx.beginPath(); ctx.arc(X(0), Y(0), msg.keep_out_mm * scale, 0, 2 * Math.PI); ctx.stroke(); ctx.setLineDash([]);
    msg.arms.forEach((arm, i) => {
      ctx.strokeStyle = i ? "#4c6a92" : "#5b6675"; ctx.lineWidth = 5; ctx.lineCap = "round";
      ctx.beginPath(); arm.points_mm.slice(0, 8).forEach((p, j) => (j ? ctx.lineTo(X(p[v.a]), Y(p[v.b])) : ctx.moveTo(X(p[v.a]), Y(p[v.b])))); ctx.stroke();
      const epm = arm.points_mm[8];
      ctx.fillStyle = "rgba(215,21,29,.8)"; ctx.beginPath(); ctx.arc(X(epm[v.a]), Y(epm[v.b]), Math.max(3, msg.epm_radius_mm * scale), 0, 2 * Math.PI); ctx.fill();
      const bx = X(arm.points_mm[0][v.a]), rightHalf = bx > (left + right) / 2;
      ctx.fillStyle = "#1b1d21"; ctx.textAlign = rightHalf ? "right" : "left";
      ctx.fillText(arm.name, bx + (rightHalf ? -8 : 8), Y(arm.points_mm[0][v.b]) + 14);
    });
    ctx.restore();
  });
}

V.seek = seek; V.play = play; V.pause = pause; V.nearestIndex = nearestIndex;
load();
