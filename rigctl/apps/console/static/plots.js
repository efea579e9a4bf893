// Time-series plots on a <canvas>, in plain JavaScript (the page must work offline: no library
// from a CDN). A TimePlot keeps the last `windowS` seconds of each series and draws them against
// labelled axes (the unit on y, seconds ago on x), with the channels' limits as dashed lines.
// With `range: [t0, t1]` (the run viewer) it draws that fixed span instead, times as they are.
"use strict";

const PALETTE = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf", "#8c564b",
                 "#e377c2", "#7f7f7f", "#bcbd22", "#393b79", "#637939", "#8c6d31", "#843c39"];

class TimePlot {
  constructor(canvas, { yLabel, windowS = 20, maxPoints = 4000, range = null, xLabel = null } = {}) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.yLabel = yLabel || "";
    this.windowS = windowS;
    this.maxPoints = maxPoints;
    this.range = range;      // [t0, t1] s: a fixed span (else the last windowS seconds)
    this.xLabel = xLabel;
    this.box = null;         // the plot area and time span as last drawn (for a cursor)
    this.series = new Map(); // name -> {t: [], y: [], color, dashed}
    this.limits = [];        // [{y, label}]
    this.dirty = true;
  }
  setYLabel(label) { this.yLabel = label; this.dirty = true; }
  setLimits(limits) { this.limits = limits; this.dirty = true; }
  add(name, t, y, { color, dashed = false } = {}) {
    let s = this.series.get(name);
    if (!s) {
      s = { t: [], y: [], color: color || PALETTE[this.series.size % PALETTE.length], dashed };
      this.series.set(name, s);
    }
    s.t.push(t); s.y.push(y);
    if (s.t.length > this.maxPoints) { s.t.splice(0, s.t.length - this.maxPoints); s.y.splice(0, s.y.length - this.maxPoints); }
    this.dirty = true;
  }
  draw() {
    if (!this.dirty) return;
    this.dirty = false;
    const { ctx, canvas } = this;
    const W = canvas.width, H = canvas.height;
    const left = 70, right = 150, top = 10, bottom = 34;
    ctx.clearRect(0, 0, W, H);
    let tMax = -Infinity;
    for (const s of this.series.values()) if (s.t.length) tMax = Math.max(tMax, s.t[s.t.length - 1]);
    if (!isFinite(tMax)) tMax = 0;
    const tMin = this.range ? this.range[0] : tMax - this.windowS;
    const span = this.range ? Math.max(1e-9, this.range[1] - this.range[0]) : this.windowS;
    let yMin = Infinity, yMax = -Infinity;
    for (const s of this.series.values()) {
      for (let i = 0; i < s.t.length; i++) if (s.t[i] >= tMin && isFinite(s.y[i])) { yMin = Math.min(yMin, s.y[i]); yMax = Math.max(yMax, s.y[i]); }
    }
    for (const l of this.limits) { yMin = Math.min(yMin, l.y); yMax = Math.max(yMax, l.y); }
    if (!isFinite(yMin)) { yMin = -1; yMax = 1; }
    if (yMax - yMin < 1e-9) { yMin -= 1; yMax += 1; }
    const pad = 0.06 * (yMax - yMin); yMin -= pad; yMax += pad;
    const x = (t) => left + (W - left - right) * (t - tMin) / span;
    this.box = { left, right: W - right, top, bottom: H - bottom, tMin, span };
    const y = (v) => top + (H - top - bottom) * (1 - (v - yMin) / (yMax - yMin));
    // axes, ticks, labels
    ctx.strokeStyle = "#9aa1ab"; ctx.lineWidth = 1; ctx.fillStyle = "#39414d";
    ctx.font = "12px system-ui, sans-serif";
    ctx.beginPath(); ctx.moveTo(left, top); ctx.lineTo(left, H - bottom); ctx.lineTo(W - right, H - bottom); ctx.stroke();
    ctx.textAlign = "right"; ctx.textBaseline = "middle";
    for (const v of niceTicks(yMin, yMax, 5)) {
      ctx.fillText(formatTick(v), left - 5, y(v));
      ctx.strokeStyle = "#eceef1"; ctx.beginPath(); ctx.moveTo(left + 1, y(v)); ctx.lineTo(W - right, y(v)); ctx.stroke();
    }
    ctx.textAlign = "center"; ctx.textBaseline = "top";
    if (this.range) for (const v of niceTicks(tMin, tMin + span, 8)) ctx.fillText(formatTick(v), x(v), H - bottom + 4);
    else for (let s = 0; s <= this.windowS; s += Math.max(1, Math.round(this.windowS / 5))) {
      ctx.fillText(`-${this.windowS - s}`, x(tMin + s), H - bottom + 4);
    }
    ctx.fillText(this.xLabel || "time (s, 0 = now)", left + (W - left - right) / 2, H - 16);
    ctx.save(); ctx.translate(14, top + (H - top - bottom) / 2); ctx.rotate(-Math.PI / 2);
    ctx.textBaseline = "middle"; ctx.fillText(this.yLabel, 0, 0); ctx.restore();
    // limits
    ctx.setLineDash([6, 4]); ctx.strokeStyle = "#c0262d";
    ctx.textAlign = "left"; ctx.textBaseline = "bottom"; ctx.fillStyle = "#c0262d";
    for (const l of this.limits) {
      ctx.beginPath(); ctx.moveTo(left, y(l.y)); ctx.lineTo(W - right, y(l.y)); ctx.stroke();
      if (l.label) ctx.fillText(l.label, left + 4, y(l.y) - 1);
    }
    ctx.setLineDash([]);
    // series
    ctx.save(); ctx.beginPath(); ctx.rect(left, top, W - left - right, H - top - bottom); ctx.clip();
    for (const s of this.series.values()) {
      ctx.strokeStyle = s.color; ctx.lineWidth = 1.4; ctx.setLineDash(s.dashed ? [4, 3] : []);
      ctx.beginPath();
      let started = false;
      for (let i = 0; i < s.t.length; i++) {
        if (s.t[i] < tMin - 1 || !isFinite(s.y[i])) continue;
        if (!started) { ctx.moveTo(x(s.t[i]), y(s.y[i])); started = true; } else ctx.lineTo(x(s.t[i]), y(s.y[i]));
      }
      ctx.stroke();
    }
    ctx.restore(); ctx.setLineDash([]);
    // legend
    ctx.textAlign = "left"; ctx.textBaseline = "middle"; ctx.font = "11px system-ui, sans-serif";
    let row = 0;
    const rows = Math.floor((H - top) / 14);
    for (const [name, s] of this.series) {
      if (row >= rows) break;
      const ly = top + 6 + 14 * row++;
      ctx.strokeStyle = s.color; ctx.setLineDash(s.dashed ? [4, 3] : []);
      ctx.beginPath(); ctx.moveTo(W - right + 8, ly); ctx.lineTo(W - right + 26, ly); ctx.stroke();
      ctx.fillStyle = "#1b1d21"; ctx.fillText(name, W - right + 30, ly);
    }
    ctx.setLineDash([]);
  }
}

function niceTicks(lo, hi, n) {
  const span = hi - lo, raw = span / n, mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => span / s <= n) || 10 * mag;
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-12; v += step) out.push(Math.abs(v) < step * 1e-9 ? 0 : v);
  return out;
}

function formatTick(v) {
  const a = Math.abs(v);
  if (a >= 1000) return v.toFixed(0);
  if (a >= 10) return v.toFixed(1).replace(/\.0$/, "");
  return v.toPrecision(3).replace(/\.?0+$/, "");
}

window.TimePlot = TimePlot;
