// Steering by hand (docs/teleoperation.md): the page's side of the daemon's `teleop` and `steer`.
// While an arrow key or W/A/S/D is held (or a gamepad's left stick is pushed), the page sends the
// input every STEER_MS; the moment the last key is let go, the stick comes back, the page loses
// its focus or is hidden, it sends "let go". The dead-man itself is the daemon's: an input counts
// there for 200 ms of its stream's clock, so a page that stops (a closed laptop, a lost network)
// stops the rig without saying anything. Arrow up is +y of the workspace, right is +x.
// `window.rigctlTeleop` exposes what the page sent (for the browser tests).
"use strict";

(function teleop() {
  const C = window.rigctlConsole;
  const STEER_MS = 50;
  const DEADZONE = 0.15;  // a gamepad stick this close to its centre is let go
  const KEYS = {
    ArrowUp: [0, 1], ArrowDown: [0, -1], ArrowLeft: [-1, 0], ArrowRight: [1, 0],
    w: [0, 1], s: [0, -1], a: [-1, 0], d: [1, 0],
  };
  const T = window.rigctlTeleop = {
    active: false, mode: null, inputs: null, sent: 0, released: 0, lastKeyUpMs: null, lastSentMs: null,
    lastReply: null, held: new Set(),
  };

  // the panel, added to the run panel's controls
  const panel = document.createElement("div");
  panel.id = "teleop";
  panel.innerHTML = `
    <h2>Steer by hand</h2>
    <div class="controls">
      <button id="teleop-start">steer</button>
      <button id="teleop-end">end</button>
      <label>level <input type="range" id="teleop-level" min="0" max="1" step="0.05" value="0.5"></label>
    </div>
    <div class="row"><span class="label">input</span> <span id="teleop-input">-</span></div>`;
  document.getElementById("run-panel").insertBefore(panel, document.getElementById("devices").previousElementSibling);
  const show = (text) => { document.getElementById("teleop-input").textContent = text; };

  function level() { return Number(document.getElementById("teleop-level").value); }

  // the input now: [heading_deg, magnitude 0..1] or null
  function current() {
    let x = 0, y = 0;
    for (const key of T.held) { x += KEYS[key][0]; y += KEYS[key][1]; }
    if (x !== 0 || y !== 0) return [Math.atan2(y, x) * 180 / Math.PI, level()];
    for (const pad of (navigator.getGamepads ? navigator.getGamepads() : [])) {
      if (!pad || pad.axes.length < 2) continue;
      const gx = pad.axes[0], gy = -pad.axes[1];  // a stick's y is down
      const push = Math.min(1, Math.hypot(gx, gy));
      if (push > DEADZONE) return [Math.atan2(gy, gx) * 180 / Math.PI, push * level()];
    }
    return null;
  }

  function asInput(value) {
    // the second component is the rig's: speed (rolling) or drive (the board)
    const names = Object.keys(T.inputs || {});
    const second = names.find((n) => n !== "heading_deg") || "speed";
    return { heading_deg: Math.round(value[0] * 100) / 100, [second]: Math.round(value[1] * 1000) / 1000 };
  }

  let sending = false, timer = null;
  function tick() {
    if (!T.active) return;
    const value = current();
    if (value) {
      sending = true;
      T.sent += 1;
      T.lastSentMs = performance.timeOrigin + performance.now();
      const input = asInput(value);
      show(JSON.stringify(input));
      C.request("steer", { input }).then((r) => { T.lastReply = r; }).catch(() => {});
    } else if (sending) {
      letGo();
    }
  }

  function letGo() {
    sending = false;
    T.released += 1;
    show("let go");
    C.request("steer", {}).catch(() => {});
  }

  function releaseAll() {
    T.held.clear();
    if (sending) letGo();
  }

  async function start() {
    const r = await C.request("teleop", {}).catch((err) => ({ ok: false, error: { message: err.message } }));
    if (!r.ok) { show(`refused: ${r.error.message}`); return; }
    T.active = true; T.mode = r.result.mode; T.inputs = r.result.inputs;
    show(`${T.mode}: hold an arrow key or W/A/S/D (or push a gamepad's left stick)`);
    if (!timer) timer = setInterval(tick, STEER_MS);
  }

  async function end() {
    releaseAll();
    T.active = false;
    if (timer) { clearInterval(timer); timer = null; }
    const r = await C.request("teleop", { end: true }).catch(() => null);
    show(r && r.ok ? "ended" : "-");
  }

  const typing = (e) => e.target && /^(INPUT|SELECT|TEXTAREA)$/.test(e.target.tagName) && e.target.type !== "range";
  document.addEventListener("keydown", (e) => {
    const key = e.key.length === 1 ? e.key.toLowerCase() : e.key;
    if (!T.active || !(key in KEYS) || typing(e)) return;
    e.preventDefault();
    if (!T.held.has(key)) { T.held.add(key); tick(); }  // a held key's repeats add nothing
  });
  document.addEventListener("keyup", (e) => {
    const key = e.key.length === 1 ? e.key.toLowerCase() : e.key;
    if (!T.held.delete(key)) return;
    T.lastKeyUpMs = performance.timeOrigin + performance.now();
    if (T.held.size === 0) tick();  // nothing held: let go now, not at the next tick
  });
  window.addEventListener("blur", releaseAll);
  document.addEventListener("visibilitychange", () => { if (document.hidden) releaseAll(); });
  document.getElementById("teleop-start").addEventListener("click", start);
  document.getElementById("teleop-end").addEventListener("click", end);
  T.start = start; T.end = end;
})();
