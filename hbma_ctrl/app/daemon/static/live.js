// The daemon's live page: reads GET /stream (server-sent events over fetch, so the bearer token can go in
// a header), draws strip charts on canvases and posts setpoints, stops and resets to the same origin.
"use strict";
const WINDOW_S = 30;            // loop time shown by the strip charts, s
const $ = (id) => document.getElementById(id);
const el = (tag, attrs = {}, text) => {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (text !== undefined) e.textContent = text;
  return e;
};
const fmt = (x, d) => (x === null || x === undefined || !isFinite(x) ? "-" : Number(x).toFixed(d));
const DIGITS = { t_s: 2, h_mm: 3, target_mm: 3, p_kpa: 2, p_est_kpa: 2, speed_pct: 1, inlet_duty: 2, outlet_duty: 2,
  rate_hz: 0, step_ms_median: 2, step_ms_p99: 2, age_ms: 0, centre_mm: 2, bend_deg: 1, direction_deg: 1 };
let token = sessionStorage.getItem("hbma-token");
let history = [];               // per chamber: [{t, h, target, p, p_est, speed, inlet, outlet}]
let names = null, layerCount = -1, ended = false, last = null, drawQueued = false, controller = null, eventsShown = "";

function headers(json) {
  const h = json ? { "Content-Type": "application/json" } : {};
  if (token) h.Authorization = "Bearer " + token;
  return h;
}
function needToken() { $("auth").hidden = false; $("conn").textContent = "token needed"; }

async function post(path, body) {
  const r = await fetch(path, { method: "POST", headers: headers(body !== undefined),
    body: body === undefined ? undefined : JSON.stringify(body) });
  if (r.status === 401) needToken();
  const reply = await r.json().catch(() => ({ error: "HTTP " + r.status }));
  return { ok: r.ok, reply };
}

// text is written only when it changes: every write costs the browser a layout and a paint
function put(e, text) { if (e.textContent !== text) e.textContent = text; }
function show(key, value, scope = document) {
  for (const e of scope.querySelectorAll(`[data-k="${key}"]`)) put(e, value);
}

function buildChambers(chambers) {
  names = chambers.map((c) => c.name || "chamber " + c.index);
  history = chambers.map(() => []);
  const box = $("chambers"), sp = $("sp-inputs");
  box.replaceChildren(); sp.replaceChildren(); sp.classList.remove("muted");
  chambers.forEach((c, i) => {
    const card = el("div", { class: "card", "data-chamber": i });
    card.append(el("h3", {}, names[i]));
    const t = el("table");
    const row = (label, keys) => {
      const tr = el("tr"); tr.append(el("th", {}, label));
      for (const k of keys) tr.append(el("td", { "data-k": k, "data-i": i }, "-"));
      t.append(tr);
    };
    row("height: estimate, target (mm)", ["h_mm", "target_mm"]);
    row("pressure: measured, estimated (kPa)", ["p_kpa", "p_est_kpa"]);
    row("pump (%), inlet, outlet (duty)", ["speed_pct", "inlet_duty", "outlet_duty"]);
    card.append(t);
    for (const k of ["h", "p", "u"]) card.append(el("canvas", { width: 420, height: 90, "data-chart": k }));
    box.append(card);
    const lab = el("label", {}, names[i] + " ");
    lab.append(el("input", { type: "number", step: "0.1", min: "0", max: "200", "data-sp": i, placeholder: "mm" }));
    sp.append(lab, " ");
  });
}

function buildLayers(n) {
  layerCount = n;
  $("pose").hidden = n === 0; $("layer-form").hidden = n === 0;
  const t = $("layers"), f = $("layer-inputs");
  while (t.rows.length > 1) t.deleteRow(1);
  f.replaceChildren();
  for (let k = 0; k < n; k++) {
    const tr = el("tr"); tr.append(el("td", {}, String(k)));
    for (const key of ["centre_mm", "bend_deg", "direction_deg"]) tr.append(el("td", { "data-k": key, "data-l": k }, "-"));
    t.append(tr);
    const lab = el("label", {}, `layer ${k}: `);
    for (const [key, ph] of [["centre_mm", "mm"], ["bend_deg", "bend deg"], ["direction_deg", "dir deg"]])
      lab.append(el("input", { type: "number", step: "0.1", "data-layer": k, "data-key": key, placeholder: ph }), " ");
    f.append(lab, " ");
  }
}

function onEvent(ev) {
  last = ev;
  record(ev);
  if (document.hidden) return;   // a tab out of sight keeps its history and draws nothing
  render(ev);
}

function record(ev) {
  if (ev.chambers.length && (!names || names.length !== ev.chambers.length)) buildChambers(ev.chambers);
  ev.chambers.forEach((c, i) => {
    const h = history[i];
    if (h.length && ev.t_s !== null && ev.t_s < h[h.length - 1].t) h.length = 0;   // a new run
    h.push({ t: ev.t_s, h: c.h_mm, target: c.target_mm, p: c.p_kpa, p_est: c.p_est_kpa,
      speed: c.speed_pct === null ? null : c.speed_pct / 100, inlet: c.inlet_duty, outlet: c.outlet_duty });
    while (h.length > 2 && h[h.length - 1].t - h[0].t > WINDOW_S) h.shift();
  });
}

function render(ev) {
  const m = $("mode"); put(m, ev.mode); if (m.className !== "mode " + ev.mode) m.className = "mode " + ev.mode;
  show("t_s", fmt(ev.t_s, DIGITS.t_s));
  for (const k of ["rate_hz", "step_ms_median", "step_ms_p99"]) show(k, fmt(ev.loop[k], DIGITS[k]));
  for (const k of ["steps", "deadline_misses", "overruns"]) show(k, String(ev.loop[k]));
  show("age_ms", fmt(ev.age_ms, DIGITS.age_ms));
  if (ev.layers.length !== layerCount) buildLayers(ev.layers.length);
  ev.chambers.forEach((c, i) => {
    const card = document.querySelector(`[data-chamber="${i}"]`);
    for (const k of ["h_mm", "target_mm", "p_kpa", "p_est_kpa", "speed_pct", "inlet_duty", "outlet_duty"])
      show(k, fmt(c[k], DIGITS[k]), card);
  });
  ev.layers.forEach((l, k) => {
    for (const key of ["centre_mm", "bend_deg", "direction_deg"])
      for (const e of document.querySelectorAll(`[data-k="${key}"][data-l="${k}"]`)) put(e, fmt(l[key], DIGITS[key]));
  });
  const counts = Object.entries(ev.faults.counts);
  put($("fault-counts"), counts.length ? counts.map(([k, v]) => `${k}: ${v}`).join(", ") : "none");
  const lines = ev.faults.latest.map((e) => `${fmt(e.t_s, 2)} s  ${e.kind}: ${e.cause}`);
  if (lines.join("\n") !== eventsShown) {
    eventsShown = lines.join("\n");
    $("events").replaceChildren(...lines.map((t) => el("li", {}, t)));
  }
  put($("conn"), `every ${ev.every_steps ?? "-"} loop periods` + (ev.lost ? `, ${ev.lost} statuses missed` : ""));
  if (!drawQueued) { drawQueued = true; requestAnimationFrame(draw); }
}

// one strip chart: series of [key, colour, label] over the history's loop time, the y range from the data
function chart(canvas, h, series, unit, fixed) {
  const g = canvas.getContext("2d"), W = canvas.width, H = canvas.height, L = 42, R = 4, T = 12, B = 14;
  g.clearRect(0, 0, W, H); g.font = "10px sans-serif";
  let lo = fixed ? fixed[0] : Infinity, hi = fixed ? fixed[1] : -Infinity;
  if (!fixed) for (const p of h) for (const [k] of series) if (p[k] !== null && isFinite(p[k])) { lo = Math.min(lo, p[k]); hi = Math.max(hi, p[k]); }
  if (!isFinite(lo)) { lo = 0; hi = 1; }
  if (hi - lo < 1e-6) { lo -= 0.5; hi += 0.5; }
  // the last WINDOW_S of loop time; a shorter run fills the width (at least 5 s)
  const t1 = h.length ? h[h.length - 1].t : 0, span = Math.max(5, Math.min(WINDOW_S, h.length ? t1 - h[0].t : 0));
  const t0 = t1 - span;
  const x = (t) => L + ((t - t0) / span) * (W - L - R), y = (v) => T + (1 - (v - lo) / (hi - lo)) * (H - T - B);
  g.strokeStyle = "#ccc"; g.strokeRect(L, T, W - L - R, H - T - B);
  g.fillStyle = "#555"; g.textAlign = "right";
  g.fillText(hi.toPrecision(3), L - 3, T + 8); g.fillText(lo.toPrecision(3), L - 3, H - B);
  g.fillText(unit, L - 3, (H + T - B) / 2 + 3);
  g.textAlign = "left"; g.fillText(`last ${span.toFixed(0)} s of loop time`, L, H - 2);
  let lx = L + 4;
  for (const [k, colour, label] of series) {
    g.strokeStyle = colour; g.lineWidth = 1.5; g.beginPath();
    let pen = false;
    for (const p of h) {
      if (p[k] === null || !isFinite(p[k])) { pen = false; continue; }
      pen ? g.lineTo(x(p.t), y(p[k])) : g.moveTo(x(p.t), y(p[k])); pen = true;
    }
    g.stroke(); g.fillStyle = colour; g.fillText(label, lx, T - 2); lx += g.measureText(label).width + 10;
  }
}

function drawPose(layers) {
  const c = $("pose-view"), g = c.getContext("2d"), r = c.width / 2 - 12, cx = c.width / 2, cy = c.height / 2;
  g.clearRect(0, 0, c.width, c.height); g.strokeStyle = "#ccc"; g.beginPath(); g.arc(cx, cy, r, 0, 2 * Math.PI); g.stroke();
  g.fillStyle = "#555"; g.font = "10px sans-serif"; g.fillText("bend direction, top view (edge: 60 deg)", 4, 10);
  const colours = ["#1565c0", "#2e7d32", "#ef6c00", "#6a1b9a", "#00838f", "#ad1457"];
  layers.forEach((l, k) => {
    if (l.bend_deg === null || l.direction_deg === null) return;
    const a = (l.direction_deg * Math.PI) / 180, len = (Math.min(Math.abs(l.bend_deg), 60) / 60) * r;
    g.strokeStyle = colours[k % colours.length]; g.lineWidth = 3; g.beginPath(); g.moveTo(cx, cy);
    g.lineTo(cx + len * Math.cos(a), cy - len * Math.sin(a)); g.stroke();
    g.fillStyle = g.strokeStyle; g.fillText(`L${k}`, cx + len * Math.cos(a) + 3, cy - len * Math.sin(a));
  });
}

function draw() {
  drawQueued = false;
  if (!last) return;
  history.forEach((h, i) => {
    const card = document.querySelector(`[data-chamber="${i}"]`);
    if (!card) return;
    chart(card.querySelector('[data-chart="h"]'), h, [["target", "#222", "target"], ["h", "#1565c0", "estimate"]], "mm");
    chart(card.querySelector('[data-chart="p"]'), h, [["p", "#c62828", "measured"], ["p_est", "#ef9a9a", "estimated"]], "kPa");
    chart(card.querySelector('[data-chart="u"]'), h, [["speed", "#2e7d32", "pump"], ["inlet", "#1565c0", "inlet"],
      ["outlet", "#ef6c00", "outlet"]], "0-1", [0, 1]);
  });
  if (last.layers.length) drawPose(last.layers);
}

async function stream() {
  if (controller) controller.abort();
  controller = new AbortController();
  const rate = Number($("rate").value) || 5;
  try {
    const r = await fetch(`/stream?rate_hz=${encodeURIComponent(rate)}`, { headers: headers(false), signal: controller.signal });
    if (r.status === 401) { needToken(); return; }
    if (!r.ok) { const e = await r.json().catch(() => ({})); $("conn").textContent = e.error || "HTTP " + r.status; throw 0; }
    $("auth").hidden = true;
    const reader = r.body.getReader(), dec = new TextDecoder();
    let buf = "";
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      buf += dec.decode(value, { stream: true });
      let cut;
      while ((cut = buf.indexOf("\n\n")) >= 0) {
        const block = buf.slice(0, cut); buf = buf.slice(cut + 2);
        const data = block.split("\n").filter((s) => s.startsWith("data:")).map((s) => s.slice(5)).join("\n");
        if (data) onEvent(JSON.parse(data));
      }
    }
    if (last && last.mode === "stopped") { ended = true; $("conn").textContent = "the daemon has stopped"; return; }
  } catch (e) {
    if (e && e.name === "AbortError") return;
  }
  if (!ended) setTimeout(stream, 1000);     // the daemon restarted, or the connection dropped: try again
}

$("sp-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  const heights = {};
  for (const inp of document.querySelectorAll("[data-sp]")) if (inp.value !== "") heights[inp.dataset.sp] = Number(inp.value);
  if (!Object.keys(heights).length) { $("sp-reply").textContent = "type a height (mm) for at least one chamber"; return; }
  await sendSetpoint({ heights_mm: heights });
});
$("layer-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  const layers = [];
  for (let k = 0; k < layerCount; k++) {
    const v = {};
    for (const inp of document.querySelectorAll(`[data-layer="${k}"]`)) if (inp.value !== "") v[inp.dataset.key] = Number(inp.value);
    if (Object.keys(v).length) layers.push({ layer: k, ...v });
  }
  if (!layers.length) { $("sp-reply").textContent = "type a layer's centre, bend and direction"; return; }
  await sendSetpoint({ layers });
});
async function sendSetpoint(body) {
  const { ok, reply } = await post("/setpoint", body);
  const p = $("sp-reply");
  p.className = ok ? "" : "error";
  if (!ok) { p.textContent = reply.error; return; }
  const hs = Object.entries(reply.applied.heights_mm).map(([i, h]) => `${names ? names[i] : i} ${fmt(h, 3)} mm`);
  const ls = reply.applied.layers.map((l) => `layer ${l.layer} ${fmt(l.centre_mm, 2)} mm, ${fmt(l.bend_deg, 1)} deg, ${fmt(l.direction_deg, 1)} deg`);
  p.textContent = "applied: " + hs.concat(ls).join("; ") + (reply.clipped.length ? "; clipped: " + reply.clipped.join("; ") : "");
  p.dataset.applied = JSON.stringify(reply.applied);
}
$("stop").addEventListener("click", async () => {
  const { ok, reply } = await post("/stop");
  $("sp-reply").className = ok ? "" : "error";
  $("sp-reply").textContent = ok ? `stop asked (${reply.reason}): the loop writes the safe command and ends` : reply.error;
});
$("reset").addEventListener("click", async () => {
  const { ok, reply } = await post("/reset");
  $("sp-reply").className = ok ? "" : "error";
  $("sp-reply").textContent = ok ? reply.detail : reply.error;
});
$("auth-form").addEventListener("submit", (e) => {
  e.preventDefault();
  token = $("token").value.trim();
  sessionStorage.setItem("hbma-token", token);
  ended = false; stream();
});
$("rate").addEventListener("change", () => { ended = false; stream(); });
document.addEventListener("visibilitychange", () => { if (!document.hidden && last) render(last); });
const asked = new URLSearchParams(location.search).get("rate_hz");   // /?rate_hz=R opens at R updates per s
if (asked) $("rate").value = asked;
stream();
