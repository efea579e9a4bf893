// Click a goal (docs/click-a-goal.md): on the camera view, click an agent, then where it should
// go; drag a goal to move it. Every change asks the daemon's `plan_goals` (goals in the camera's
// pixels: the daemon maps them to the floor with the rig's calibration and plans from where it
// last saw the agents, `status.tracked`), and the planned paths are drawn over the camera view in
// an SVG of the camera's pixels; "execute goals" runs the loaded plan with the ordinary `execute`.
// An unreachable goal shows the daemon's one line instead of a path.
// `window.rigctlGoals` exposes what the page planned (for the browser tests).
"use strict";

(function goals() {
  const SVG = "http://www.w3.org/2000/svg";
  const COLORS = ["#ff3b3b", "#3bc4ff", "#ffd23b", "#7cff3b", "#ff7cf0", "#ffffff"];
  const PICK_PX = 20;  // a click this close to an agent (camera px, beyond its radius) picks it
  const SETTLE_MS = 300;  // goals changed within this are planned together
  const C = window.rigctlConsole;
  const G = window.rigctlGoals = { selected: null, goals: new Map(), plan: null, planId: null,
    reason: null, requests: 0, replies: 0 };

  const canvas = document.getElementById("camera");
  const wrap = document.createElement("div");
  wrap.id = "goals-view";
  wrap.style.position = "relative";
  canvas.replaceWith(wrap);
  wrap.append(canvas);
  const svg = document.createElementNS(SVG, "svg");
  svg.id = "goals-overlay";
  // the canvas shows its picture as `object-fit: contain` (console.css): the same fit here
  svg.setAttribute("preserveAspectRatio", "xMidYMid meet");
  svg.setAttribute("aria-label", "clicked goals and planned paths");
  Object.assign(svg.style, { position: "absolute", left: "0", top: "0", width: "100%",
    height: "100%", cursor: "crosshair", touchAction: "none" });
  wrap.append(svg);

  const bar = document.createElement("div");
  bar.className = "controls";
  bar.id = "goals-controls";
  const execute = button("goals-execute", "execute goals", "run the plan to the clicked goals");
  const clear = button("goals-clear", "clear goals", "forget the clicked goals and the plan");
  const line = document.createElement("div");
  line.id = "goals-reply"; line.className = "reply";
  line.textContent = "click an agent, then its goal";
  bar.append(execute, clear);
  wrap.after(bar, line);
  execute.disabled = true;

  function button(id, text, title) {
    const b = document.createElement("button");
    b.id = id; b.textContent = text; b.title = title;
    return b;
  }

  function resolution() {
    const res = C.hello && C.hello.rig.camera && C.hello.rig.camera.resolution;
    return res || [canvas.width, canvas.height];
  }

  // where the agents are, in the camera's pixels: where plan_goals starts from (the daemon's
  // latest tracking), else what the camera or the emulator shows now
  function agentsPx() {
    const tracked = C.status && C.status.tracked;
    if (tracked && tracked.positions_px) return tracked.positions_px;
    if (C.lastFrame) return C.lastFrame.tracked_px;
    return C.agents ? C.agents.tracked_px : [];
  }

  function toCamera(event) {
    const p = svg.createSVGPoint();
    p.x = event.clientX; p.y = event.clientY;
    const q = p.matrixTransform(svg.getScreenCTM().inverse());
    return [q.x, q.y];
  }

  function say(text, error) {
    line.textContent = text;
    line.className = error ? "reply error" : "reply";
  }

  // -- clicks and drags ---------------------------------------------------------------------------
  let dragging = null;
  svg.addEventListener("pointerdown", (event) => {
    if (C.state !== "idle") { say("goals are planned while the rig is idle", true); return; }
    const at = toCamera(event);
    const goal = event.target.dataset && event.target.dataset.goal;
    if (goal !== undefined) {  // a goal marker: drag it
      dragging = Number(goal);
      svg.setPointerCapture(event.pointerId);
      return;
    }
    const agents = agentsPx() || [];
    let nearest = null, best = Infinity;
    agents.forEach(([x, y], i) => {
      const d = Math.hypot(x - at[0], y - at[1]);
      if (d < best) { best = d; nearest = i; }
    });
    if (nearest !== null && best <= pickRadius(nearest)) {
      G.selected = nearest;
      say(`agent #${nearest}: click where it should go`);
    } else if (G.selected !== null) {
      G.goals.set(G.selected, at);
      G.selected = null;
      changed();
    } else {
      say("click an agent first (a filled disc), then its goal", true);
    }
    draw();
  });
  svg.addEventListener("pointermove", (event) => {
    if (dragging === null) return;
    G.goals.set(dragging, toCamera(event));
    draw();
  });
  svg.addEventListener("pointerup", () => {
    if (dragging === null) return;
    dragging = null;
    changed();
  });

  function pickRadius(i) {
    const radii = C.scene && C.scene.radii_px;
    return Math.max(PICK_PX, (radii && radii[i]) || 0);
  }

  // -- planning -------------------------------------------------------------------------------------
  let timer = null, inFlight = false, again = false;
  function changed() {
    G.plan = null; G.planId = null; G.reason = null;
    execute.disabled = true;
    clearTimeout(timer);
    timer = setTimeout(plan, SETTLE_MS);
    draw();
  }

  async function plan() {
    if (!G.goals.size) return;
    if (inFlight) { again = true; return; }
    inFlight = true; again = false;
    const goals = [...G.goals].map(([agent, px]) => ({ agent, px: px.map((v) => +v.toFixed(2)) }));
    say("planning...");
    G.requests++;
    let reply;
    try { reply = await C.request("plan_goals", { goals }); }
    catch (err) { reply = { ok: false, error: { code: "disconnected", message: err.message } }; }
    G.replies++;
    inFlight = false;
    if (again) { plan(); return; }  // the goals changed meanwhile: this plan is for old ones
    if (reply.ok) {
      const r = reply.result;
      G.plan = r; G.planId = r.plan_id; G.reason = null;
      const steps = r.plan.moves ? `${r.plan.moves.length} moves` : `${r.plan.segments.length} segments`;
      say(`planned: ${steps}, ${r.distance_mm.toFixed(2)} mm from the goals (plan ${r.plan_id})`);
      execute.disabled = !C.authenticated;
    } else {
      G.plan = null; G.planId = null; G.reason = reply.error.message;
      say(`${reply.error.code}: ${reply.error.message}`, true);
    }
    draw();
  }

  execute.addEventListener("click", async () => {
    if (!G.planId) return;
    execute.disabled = true;
    const reply = await C.request("execute", { plan_id: G.planId });
    if (reply.ok) {  // the run's scene draws its plan from here on; the next goals start afresh
      say(`executing plan ${G.planId}`);
      G.goals.clear(); G.selected = null; G.plan = null; G.planId = null;
      draw();
    } else { say(`execute refused: ${reply.error.code}: ${reply.error.message}`, true); execute.disabled = false; }
  });
  clear.addEventListener("click", () => {
    G.goals.clear(); G.selected = null; G.plan = null; G.planId = null; G.reason = null;
    execute.disabled = true;
    say("click an agent, then its goal");
    draw();
  });

  // -- drawing (SVG in the camera's pixels, over the canvas) ------------------------------------------
  function draw() {
    const shown = !canvas.hidden;  // an "arms" scene has no camera view to click on
    svg.style.display = shown ? "" : "none";
    bar.hidden = !shown; line.hidden = !shown;
    const [w, h] = resolution();
    svg.setAttribute("viewBox", `0 0 ${w} ${h}`);
    svg.replaceChildren();
    const s = w / 640;  // strokes and markers keep their size on the page
    if (G.plan && G.plan.paths_px) {
      G.plan.paths_px.forEach((path, i) => {
        const el = document.createElementNS(SVG, "polyline");
        el.setAttribute("class", "planned-path");
        el.dataset.agent = String(i);
        el.setAttribute("points", path.map(([x, y]) => `${x},${y}`).join(" "));
        Object.assign(el.style, { fill: "none", stroke: COLORS[i % COLORS.length],
          strokeWidth: String(3 * s), opacity: "0.9" });
        svg.append(el);
      });
    }
    const agents = agentsPx() || [];
    agents.forEach(([x, y], i) => {  // what a click picks: where plan_goals starts from
      const dot = document.createElementNS(SVG, "circle");
      dot.setAttribute("class", "tracked-agent");
      dot.setAttribute("cx", x); dot.setAttribute("cy", y); dot.setAttribute("r", String(5 * s));
      Object.assign(dot.style, { fill: COLORS[i % COLORS.length], stroke: "#fff",
        strokeWidth: String(1.5 * s), pointerEvents: "none" });
      svg.append(dot);
    });
    if (G.selected !== null && agents[G.selected]) {
      const [x, y] = agents[G.selected];
      const ring = document.createElementNS(SVG, "circle");
      ring.setAttribute("class", "selected-agent");
      ring.setAttribute("cx", x); ring.setAttribute("cy", y); ring.setAttribute("r", pickRadius(G.selected));
      Object.assign(ring.style, { fill: "none", stroke: "#fff", strokeWidth: String(2 * s),
        strokeDasharray: `${4 * s} ${3 * s}` });
      svg.append(ring);
    }
    for (const [agent, [x, y]] of G.goals) {
      const mark = document.createElementNS(SVG, "circle");
      mark.setAttribute("class", "clicked-goal");
      mark.dataset.goal = String(agent);
      mark.setAttribute("cx", x); mark.setAttribute("cy", y); mark.setAttribute("r", String(8 * s));
      Object.assign(mark.style, { fill: "rgba(0,0,0,.2)", stroke: COLORS[agent % COLORS.length],
        strokeWidth: String(3 * s), cursor: "move" });
      svg.append(mark);
    }
  }

  // the tracked positions come with the status poll: the selection ring follows them
  setInterval(draw, 500);
  draw();
})();
