// The operator console's page: one WebSocket to the console (the daemon's telemetry as it came,
// `status` for every page, replies to this page's requests), drawn on canvases. No state of its
// own beyond what the daemon said last: every button sends the daemon's own command.
// `window.rigctlConsole` exposes what the page saw (for the browser tests and bench/console.py):
// frame latencies from capture to the overlay drawn, on the browser's own clock.
"use strict";

const $ = (id) => document.getElementById(id);
const nowMs = () => performance.timeOrigin + performance.now();

const C = window.rigctlConsole = {
  hello: null, status: null, state: "unknown", scene: null, agents: null, frame: null,
  frames: 0, frameLatenciesMs: [], frameReceivedMs: [], lastFrame: null, estops: [], replies: 0, log: [],
  authenticated: false, connected: false,
};

// the token comes in the URL's fragment (never sent to a server), kept for this tab only
(function takeToken() {
  const fromHash = new URLSearchParams(location.hash.slice(1)).get("token");
  if (fromHash) {
    sessionStorage.setItem("rigctl-token", fromHash);
    history.replaceState(null, "", location.pathname + location.search);
  }
})();

let ws = null, nextId = 1;
const pending = new Map();

function connect() {
  ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws");
  ws.onopen = () => ws.send(JSON.stringify({ type: "hello", token: sessionStorage.getItem("rigctl-token") || "" }));
  ws.onmessage = (event) => handle(JSON.parse(event.data));
  ws.onclose = () => {
    C.connected = false;
    showState("disconnected", "no connection to the console: retrying");
    for (const [, p] of pending) p.reject(new Error("disconnected"));
    pending.clear();
    setTimeout(connect, 1000);
  };
}

function request(cmd, args = {}) {
  return new Promise((resolve, reject) => {
    if (!ws || ws.readyState !== WebSocket.OPEN) { reject(new Error("not connected")); return; }
    const id = nextId++;
    pending.set(id, { resolve, reject });
    ws.send(JSON.stringify({ id, cmd, args }));
  });
}

C.request = request;  // for scripts driving the page (bench/console.py)

async function control(cmd, args = {}) {
  const reply = $("reply");
  try {
    const r = await request(cmd, args);
    if (r.ok) { reply.className = "reply"; reply.textContent = `${cmd}: ${summarise(r.result)}`; }
    else { reply.className = "reply error"; reply.textContent = `${cmd} refused: ${r.error.code}: ${r.error.message}`; }
    return r;
  } catch (err) {
    reply.className = "reply error"; reply.textContent = `${cmd}: ${err.message}`;
    return { ok: false };
  }
}

function summarise(result) {
  if (result && typeof result === "object") {
    if (result.state) return `state ${result.state}` + (result.pending ? ` (pending: ${result.pending})` : "");
    if (result.plan_id) return `plan ${result.plan_id}`;
  }
  return "done";
}

// -- messages ------------------------------------------------------------------------------------
function handle(msg) {
  switch (msg.topic) {
    case "console.hello": return onHello(msg);
    case "console.status": return onStatus(msg.status);
    case "console.scene": C.scene = msg; return drawCameraIdle();
    case "console.reply": {
      C.replies++;
      const p = pending.get(msg.id);
      if (p) { pending.delete(msg.id); p.resolve(msg); }
      return;
    }
    case "console.arms": return drawArms(msg);
    case "console.refused": showState("refused", msg.reason); return;
    case "state": C.state = msg.state; showState(msg.state, describeReason(msg)); addLog(`state ${msg.state}` + (msg.reason ? `: ${describeReason(msg)}` : ""), msg.state === "faulted" ? "fault" : ""); return;
    case "fault": addLog(`FAULT ${msg.device || "?"}: ${msg.reason} (${msg.kind})`, "fault"); return;
    case "log": addLog(`${msg.level.toLowerCase()}: ${msg.message}`, msg.level === "ERROR" ? "fault" : "warning"); return;
    case "actuators": return onActuators(msg);
    case "field": return onField(msg);
    case "stream": return onStream(msg);
    case "agents": C.agents = msg; updateAgents(); if (!C.frame || nowMs() - C.frame.drawnAt > 1000) drawCameraIdle(); return;
    case "frame": return onFrame(msg);
  }
}

function describeReason(s) { return s.reason ? (s.device ? `${s.device}: ${s.reason}` : s.reason) : ""; }

function showState(state, reason) {
  const el = $("state");
  el.textContent = state; el.dataset.state = state; el.className = `state state-${state}`;
  $("reason").textContent = reason || "";
}

let plots = null;
function onHello(msg) {
  C.hello = msg; C.connected = true; C.authenticated = msg.authenticated;
  const rig = msg.rig;
  $("rig-name").textContent = rig.name;
  $("rig-kind").textContent = `${rig.kind}${rig.emulated ? " (emulated)" : ""}, ${rig.rate_hz} Hz`;
  $("access").textContent = msg.authenticated ? "control enabled (token)" : "watch only: open the page with the token to control";
  for (const id of ["execute", "pause", "pause-now", "resume", "abort", "reset", "load-choice", "estop"]) {
    if (!msg.authenticated) $(id).title = "needs the token";
  }
  const select = $("plan-choice");
  select.length = 1;
  for (const name of msg.plans) select.add(new Option(name, name));
  // the scene is the rig kind's: "arms" (the arm views) or "camera" (the image and the plan)
  const arms = rig.scene === "arms";
  $("camera").hidden = arms; $("arms").hidden = !arms;
  $("view-title").textContent = arms ? "Arms (top and side views)" : "Camera";
  $("legend").textContent = arms
    ? "grey: arm links (joint origins); red: EPMs; dashed: keep-out sphere"
    : "filled: tracked (camera), ring: expected by the plan, x: goal, dashed: planned path, grey: obstacles";
  // the field plot appears with the first `field` telemetry (a daemon that knows its coils'
  // actuation matrix sends it)
  $("field-title").hidden = true; $("plot-field").hidden = true;
  const units = [...new Set(rig.channels.map((c) => c.unit))];
  plots = {
    actuators: new TimePlot($("plot-actuators"), { yLabel: units.join(", ") }),
    field: new TimePlot($("plot-field"), { yLabel: "B (mT)" }),
    stream: new TimePlot($("plot-stream"), { yLabel: "period error (ms)" }),
  };
  const highs = [...new Set(rig.channels.map((c) => c.high).filter((v) => v !== null))];
  const lows = [...new Set(rig.channels.map((c) => c.low).filter((v) => v !== null))];
  const limits = [];
  if (highs.length === 1) limits.push({ y: highs[0], label: `limit ${highs[0]} ${units[0]}` });
  if (lows.length === 1) limits.push({ y: lows[0], label: `limit ${lows[0]} ${units[0]}` });
  plots.actuators.setLimits(limits);
  if (msg.status) onStatus(msg.status);
  if (!arms) drawCameraIdle();
  refreshRuns();
}

function onStatus(status) {
  C.status = status;
  if (!status) return;
  if (C.state !== status.state || !$("state").dataset.state || $("state").dataset.state !== status.state) {
    C.state = status.state; showState(status.state, describeReason(status));
  }
  const run = status.run;
  if (run) {
    $("plan").textContent = `${run.name || run.plan_id || run.kind} (${run.plan_id || run.kind})`;
    const unit = "moves" in run ? "move" : "segment";
    const total = run[unit + "s"];
    $("step").textContent = `${unit} ${run.move + 1} of ${total ?? "?"}, sample ${run.sample} of ${run.samples ?? "?"}`;
    const done = run.samples ? Math.max(0, Math.min(1, run.sample / run.samples)) : 0;
    $("progress-bar").style.width = `${(100 * done).toFixed(1)}%`;
  } else {
    const last = status.last_run;
    $("plan").textContent = last ? `last: ${last.plan_id} (${last.reached ? "reached" : "not reached"})` : "-";
    $("step").textContent = "-";
    $("progress-bar").style.width = "0";
  }
  const body = $("devices").tBodies[0];
  body.textContent = "";
  for (const d of status.devices || []) {
    const tr = body.insertRow();
    tr.insertCell().textContent = d.name;
    const h = tr.insertCell(); h.textContent = d.health; h.className = `health-${d.health}`;
    tr.insertCell().textContent = d.detail || "";
  }
  for (const [id, states] of Object.entries(ENABLED)) $(id).disabled = !C.authenticated || !states.includes(status.state);
  if (status.run) $("reset").disabled = true;  // the run is still stopping: the daemon says busy
  $("execute").disabled = !C.authenticated || status.state !== "idle" || !loadedPlan;
  $("estop").disabled = false;
}

const ENABLED = {
  pause: ["running"], "pause-now": ["running", "paused"], resume: ["paused"],
  abort: ["running", "paused", "suspended"], reset: ["faulted", "estopped"],
};

// -- plots -----------------------------------------------------------------------------------------
function onActuators(msg) {
  if (!plots) return;
  const many = msg.channels.length > 6;
  const k = msg.times.length;
  const picks = k <= 5 ? [...Array(k).keys()] : [0, 1, 2, 3, 4].map((i) => Math.round(i * (k - 1) / 4));
  for (const i of picks) {
    msg.channels.forEach((name, j) => {
      plots.actuators.add(`${name} meas.`, msg.times[i], msg.measured[i][j]);
      if (!many) plots.actuators.add(`${name} cmd.`, msg.times[i], msg.commanded[i][j], { dashed: true });
    });
  }
}

function onField(msg) {
  if (!plots) return;
  $("field-title").hidden = false; $("plot-field").hidden = false;
  ["x", "y", "z"].forEach((axis, j) => {
    plots.field.add(`B${axis} meas.`, msg.t, msg.measured_mT[j]);
    plots.field.add(`B${axis} cmd.`, msg.t, msg.commanded_mT[j], { dashed: true });
  });
}

function onStream(msg) {
  if (!plots) return;
  plots.stream.add("p99", msg.t, msg.period_error_p99_us / 1000);
  plots.stream.add("p50", msg.t, msg.period_error_p50_us / 1000);
  const late = msg.cycles ? (100 * msg.late_cycles / msg.cycles).toFixed(2) : "0";
  $("stream-title").textContent = `Stream period error (late cycles: ${late} %)`;
}

// the plots are redrawn 5 times a second, not at every animation frame: a page watching must
// cost its machine little (it may be the rig's own computer)
const PLOT_PERIOD_MS = 200;
setInterval(() => { if (plots) for (const p of Object.values(plots)) p.draw(); }, PLOT_PERIOD_MS);

// -- the agents ------------------------------------------------------------------------------------
let agentsDrawnAt = 0;
function updateAgents() {
  // tracked: the camera's (the last frame drawn, when fresh), else the daemon's `agents`
  const now = nowMs();
  if (now - agentsDrawnAt < 200) return;  // a table at 5 Hz is plenty to read
  agentsDrawnAt = now;
  const a = C.agents;
  const fresh = C.lastFrame && now - C.lastFrame.drawn_at_ms < 1000;
  const tracked = fresh ? C.lastFrame.positions_mm : a && a.tracked_mm;
  const body = $("agents").tBodies[0];
  body.textContent = "";
  if (!tracked) return;
  tracked.forEach((p, i) => {
    const e = a && a.expected_mm ? a.expected_mm[i] : null;
    const tr = body.insertRow();
    tr.insertCell().textContent = `#${i}`;
    tr.insertCell().textContent = `${p[0].toFixed(1)}, ${p[1].toFixed(1)}`;
    tr.insertCell().textContent = e ? `${e[0].toFixed(1)}, ${e[1].toFixed(1)}` : "-";
    tr.insertCell().textContent = e ? Math.hypot(p[0] - e[0], p[1] - e[1]).toFixed(2) : "-";
  });
}

// -- the camera ------------------------------------------------------------------------------------
const AGENT_COLORS = ["#ff3b3b", "#3bc4ff", "#ffd23b", "#7cff3b", "#ff7cf0", "#ffffff"];

function onFrame(msg) {
  const receivedAt = nowMs();
  const bytes = Uint8Array.from(atob(msg.jpeg_b64), (c) => c.charCodeAt(0));
  createImageBitmap(new Blob([bytes], { type: "image/jpeg" })).then((bitmap) => {
    const canvas = $("camera");
    if (canvas.width !== bitmap.width || canvas.height !== bitmap.height) {
      canvas.width = bitmap.width; canvas.height = bitmap.height;
    }
    const ctx = canvas.getContext("2d");
    ctx.drawImage(bitmap, 0, 0);
    bitmap.close();
    drawOverlays(ctx, canvas.width / msg.width, msg.tracked_px, msg.lost);
    const drawnAt = nowMs();
    const latency = drawnAt - 1000 * msg.t_source_unix;
    C.frameLatenciesMs.push(latency);
    C.frameReceivedMs.push(receivedAt - 1000 * msg.t_source_unix);  // capture -> on the page
    if (C.frameLatenciesMs.length > 5000) { C.frameLatenciesMs.shift(); C.frameReceivedMs.shift(); }
    C.frames++;
    C.frame = { drawnAt };
    C.lastFrame = { frame: msg.frame, seq: msg.seq, positions_mm: msg.positions_mm, tracked_px: msg.tracked_px, latency_ms: latency, drawn_at_ms: drawnAt };
    updateAgents();
  });
}

function drawCameraIdle() {
  // no fresh frame: the scene and the agents' positions on black, in the camera's pixels
  const canvas = $("camera");
  if (canvas.hidden) return;
  const res = C.hello && C.hello.rig.camera && C.hello.rig.camera.resolution;
  const ctx = canvas.getContext("2d");
  const scale = res ? canvas.width / res[0] : 1;
  ctx.fillStyle = "#0c0d10"; ctx.fillRect(0, 0, canvas.width, canvas.height);
  drawOverlays(ctx, scale, C.agents ? C.agents.tracked_px : null, null);
  ctx.fillStyle = "#9aa1ab"; ctx.font = "14px system-ui, sans-serif"; ctx.textAlign = "left";
  ctx.fillText("no camera frame (idle, or an open-loop run)", 10, 20);
}

function drawOverlays(ctx, s, trackedPx, lost) {
  const scene = C.scene;
  ctx.lineWidth = 2;
  const poly = (pts) => { ctx.beginPath(); pts.forEach(([x, y], i) => (i ? ctx.lineTo(x * s, y * s) : ctx.moveTo(x * s, y * s))); ctx.closePath(); };
  if (scene) {
    if (scene.boundary.length) { ctx.strokeStyle = "rgba(255,255,255,.8)"; poly(scene.boundary); ctx.stroke(); }
    ctx.fillStyle = "rgba(160,160,170,.35)"; ctx.strokeStyle = "rgba(200,200,210,.8)";
    for (const o of scene.obstacles) { poly(o); ctx.fill(); ctx.stroke(); }
    scene.paths.forEach((path, i) => {
      ctx.strokeStyle = AGENT_COLORS[i % AGENT_COLORS.length]; ctx.setLineDash([6, 5]);
      ctx.beginPath(); path.forEach(([x, y], j) => (j ? ctx.lineTo(x * s, y * s) : ctx.moveTo(x * s, y * s))); ctx.stroke();
    });
    ctx.setLineDash([]);
    scene.goals.forEach(([x, y], i) => {
      ctx.strokeStyle = AGENT_COLORS[i % AGENT_COLORS.length]; const r = 7;
      ctx.beginPath(); ctx.moveTo(x * s - r, y * s - r); ctx.lineTo(x * s + r, y * s + r); ctx.moveTo(x * s + r, y * s - r); ctx.lineTo(x * s - r, y * s + r); ctx.stroke();
    });
  }
  const radius = (i) => Math.max(4, ((scene && scene.radii_px[i]) || 6) * s);
  const expected = C.agents && C.agents.expected_px;
  if (expected) expected.forEach(([x, y], i) => {
    ctx.strokeStyle = AGENT_COLORS[i % AGENT_COLORS.length]; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.arc(x * s, y * s, radius(i) + 3, 0, 2 * Math.PI); ctx.stroke();
  });
  if (trackedPx) trackedPx.forEach(([x, y], i) => {
    ctx.fillStyle = lost && lost[i] ? "rgba(128,128,128,.7)" : AGENT_COLORS[i % AGENT_COLORS.length];
    ctx.globalAlpha = 0.75; ctx.beginPath(); ctx.arc(x * s, y * s, radius(i), 0, 2 * Math.PI); ctx.fill(); ctx.globalAlpha = 1;
    ctx.fillStyle = "#fff"; ctx.font = "bold 13px system-ui, sans-serif"; ctx.textAlign = "left";
    ctx.fillText(`#${i}${lost && lost[i] ? " lost" : ""}`, x * s + radius(i) + 3, y * s - radius(i));
  });
}

// -- the arms scene -------------------------------------------------------------------------------
function drawArms(msg) {
  C.arms = msg;
  const canvas = $("arms"), ctx = canvas.getContext("2d");
  const W = canvas.width, H = canvas.height;
  ctx.clearRect(0, 0, W, H);
  const views = [{ title: "top view", a: 0, b: 1, xl: "x (mm)", yl: "y (mm)" }, { title: "side view", a: 0, b: 2, xl: "x (mm)", yl: "z (mm)" }];
  const pts = msg.arms.flatMap((arm) => arm.points_mm);
  views.forEach((v, k) => {
    const left = k * W / 2 + 56, right = (k + 1) * W / 2 - 12, top = 24, bottom = H - 40;
    const xs = pts.map((p) => p[v.a]).concat([-msg.keep_out_mm, msg.keep_out_mm]);
    const ys = pts.map((p) => p[v.b]).concat([-msg.keep_out_mm, msg.keep_out_mm]);
    const lo = [Math.min(...xs), Math.min(...ys)], hi = [Math.max(...xs), Math.max(...ys)];
    const span = Math.max(hi[0] - lo[0], hi[1] - lo[1]) * 1.1 + 1;
    const cx = (lo[0] + hi[0]) / 2, cy = (lo[1] + hi[1]) / 2;
    const scale = Math.min(right - left, bottom - top) / span;
    const ox = (left + right) / 2, oy = (top + bottom) / 2;
    const X = (x) => ox + (x - cx) * scale, Y = (y) => oy - (y - cy) * scale;
    ctx.strokeStyle = "#9aa1ab"; ctx.lineWidth = 1; ctx.strokeRect(left, top, right - left, bottom - top);
    ctx.fillStyle = "#39414d"; ctx.font = "12px system-ui, sans-serif"; ctx.textAlign = "center";
    ctx.fillText(v.title, (left + right) / 2, 14);
    ctx.fillText(v.xl, (left + right) / 2, H - 8);
    for (const t of niceTicks(cx - (right - left) / 2 / scale, cx + (right - left) / 2 / scale, 4)) {
      if (X(t) >= left && X(t) <= right) ctx.fillText(formatTick(t), X(t), bottom + 14);
    }
    ctx.textAlign = "right"; ctx.textBaseline = "middle";
    for (const t of niceTicks(cy - (bottom - top) / 2 / scale, cy + (bottom - top) / 2 / scale, 4)) {
      if (Y(t) >= top && Y(t) <= bottom) ctx.fillText(formatTick(t), left - 4, Y(t));
    }
    ctx.save(); ctx.translate(k * W / 2 + 12, (top + bottom) / 2); ctx.rotate(-Math.PI / 2); ctx.textAlign = "center"; ctx.fillText(v.yl, 0, 0); ctx.restore();
    ctx.textBaseline = "alphabetic";
    ctx.save(); ctx.beginPath(); ctx.rect(left, top, right - left, bottom - top); ctx.clip();
    ctx.setLineDash([5, 4]); ctx.strokeStyle = "#c0262d";
    ctx.beginPath(); ctx.arc(X(0), Y(0), msg.keep_out_mm * scale, 0, 2 * Math.PI); ctx.stroke(); ctx.setLineDash([]);
    msg.arms.forEach((arm, i) => {
      ctx.strokeStyle = i ? "#4c6a92" : "#5b6675"; ctx.lineWidth = 5; ctx.lineCap = "round";
      ctx.beginPath(); arm.points_mm.slice(0, 8).forEach((p, j) => (j ? ctx.lineTo(X(p[v.a]), Y(p[v.b])) : ctx.moveTo(X(p[v.a]), Y(p[v.b])))); ctx.stroke();
      const epm = arm.points_mm[8];
      ctx.fillStyle = "rgba(215,21,29,.8)"; ctx.beginPath(); ctx.arc(X(epm[v.a]), Y(epm[v.b]), Math.max(3, msg.epm_radius_mm * scale), 0, 2 * Math.PI); ctx.fill();
      const bx = X(arm.points_mm[0][v.a]), right_half = bx > (left + right) / 2;
      ctx.fillStyle = "#1b1d21"; ctx.textAlign = right_half ? "right" : "left";
      ctx.fillText(arm.name, bx + (right_half ? -8 : 8), Y(arm.points_mm[0][v.b]) + 14);
    });
    ctx.restore();
  });
}

// -- log and runs -------------------------------------------------------------------------------
function addLog(text, cls) {
  const li = document.createElement("li");
  li.textContent = `${new Date().toLocaleTimeString()} ${text}`;
  if (cls) li.className = cls;
  const log = $("log");
  log.prepend(li);
  while (log.children.length > 300) log.lastChild.remove();
  C.log.push(text);
}

async function refreshRuns() {
  let r;
  try { r = await request("runs", { limit: 20 }); } catch { return; }
  if (!r.ok) return;
  const body = $("runs").tBodies[0];
  body.textContent = "";
  for (const run of r.result) {
    const tr = body.insertRow();
    const name = tr.insertCell(); name.textContent = run.id;
    tr.insertCell().textContent = !run.finished ? "unfinished" : run.faults && run.faults.length ? "fault" : run.reached ? "reached" : "missed";
    tr.insertCell().textContent = run.duration_s == null ? "" : run.duration_s.toFixed(1);
    const links = tr.insertCell();
    const report = document.createElement("a");
    report.href = `/runs/${encodeURIComponent(run.id)}/report.png`; report.target = "_blank"; report.textContent = "report";
    const summary = document.createElement("a"); summary.href = "#"; summary.textContent = "summary";
    summary.onclick = async (e) => { e.preventDefault(); const s = await request("run", { run: run.id }); $("run-summary").textContent = s.ok ? JSON.stringify(s.result.summary, null, 1) : s.error.message; };
    const view = document.createElement("a");  // the run viewer (records.py, viewer.js)
    const token = sessionStorage.getItem("rigctl-token");  // the new tab keeps no sessionStorage
    view.href = `/viewer?run=${encodeURIComponent(run.id)}${token ? `#token=${token}` : ""}`; view.target = "_blank"; view.textContent = "view";
    links.append(view, " ", report, " ", summary);
  }
}

// -- controls --------------------------------------------------------------------------------------
let loadedPlan = null;
function planLoaded(r) {
  if (r.ok) { loadedPlan = r.result.plan_id; $("loaded").textContent = `${r.result.name || ""} (${loadedPlan})`; if (C.status) onStatus(C.status); }
}

function estop() {
  const clicked = nowMs();
  const entry = { clicked_ms: clicked, replied_ms: null, ok: null };
  C.estops.push(entry);
  control("estop").then((r) => { entry.replied_ms = nowMs(); entry.ok = r.ok; entry.result = r.result || r.error; });
}

$("estop").addEventListener("click", estop);
document.addEventListener("keydown", (e) => { if (e.key === "Escape") { e.preventDefault(); estop(); } });
$("execute").addEventListener("click", () => control("execute", { plan_id: loadedPlan }));
$("pause").addEventListener("click", () => control("pause", { immediate: false }));
$("pause-now").addEventListener("click", () => control("pause", { immediate: true }));
$("resume").addEventListener("click", () => control("resume"));
$("abort").addEventListener("click", () => control("abort"));
$("reset").addEventListener("click", () => control("reset"));
$("refresh-runs").addEventListener("click", refreshRuns);
$("load-choice").addEventListener("click", async () => {
  const name = $("plan-choice").value;
  if (name) planLoaded(await control("load_file", { name }));
});
$("plan-file").addEventListener("change", async (e) => {
  const file = e.target.files[0];
  if (!file) return;
  let plan;
  try { plan = JSON.parse(await file.text()); } catch (err) { $("reply").className = "reply error"; $("reply").textContent = `${file.name}: not JSON (${err.message})`; return; }
  planLoaded(await control("load", { plan }));
  e.target.value = "";
});

connect();
