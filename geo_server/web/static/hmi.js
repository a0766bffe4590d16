// geo-server web HMI (docs/web.md): one WebSocket, `live` pushes 10 times a second.
"use strict";

const COLORS = ["#0b6bcb", "#d9480f", "#2b8a3e", "#862e9c", "#e67700", "#c2255c"];
const MARK = "#c62828";
const TREND_SECONDS = 600;
const state = { hello: null, axes: [], trends: [], tables: [], tablePlots: [], live: null,
                pushes: 0 };

const $ = (sel, root = document) => root.querySelector(sel);
const el = (tag, attrs = {}, ...kids) => {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") e.className = v; else if (k === "text") e.textContent = v;
    else e.setAttribute(k, v);
  }
  for (const k of kids) e.append(k);
  return e;
};

function fmt(v, digits) {
  if (v === null || v === undefined) return "–";
  if (typeof v === "boolean") return v ? "TRUE" : "FALSE";
  return Number(v).toFixed(digits);
}

// tick labels: uPlot's default shows at most 3 decimals (a rotary axis' 0.0001° is 0)
const ticks = (u, splits) => splits.map((v) => (v === null ? "" : Math.abs(v) >= 1000
  ? v.toLocaleString("en") : String(+v.toFixed(8))));

// time ticks as a 24-hour clock of the browser's time zone
const clock = (u, splits) => splits.map((t) => new Date(t * 1000).toLocaleTimeString("en-GB"));

const liveAxis = (axis) => (state.live ? state.live.axes[String(axis)] : null) || null;
const axisInfo = (axis) => state.axes.find((a) => a.axis === axis) || { name: `axis ${axis}`, rotary: false };

// ---------------------------------------------------------------- axis cards

// field, label, decimals on a linear axis, on a rotary axis, quantity
const AXIS_ROWS = [
  ["command_position", "command position", 4, 4, "pos"],
  ["output_position", "output position", 4, 4, "pos"],
  ["total_offset", "total offset", 1, 4, "off"],
  ["velocity", "velocity", 3, 3, "vel"],
];
const TWIN_ROWS = [
  ["residual", "residual error (twin)", 2, 5, "off"],
  ["sensor_temperature", "sensor (twin)", 2, 2, "°C"],
];

function unitOf(quantity, rotary) {
  if (quantity === "pos") return rotary ? "°" : "mm";
  if (quantity === "off") return rotary ? "°" : "µm";
  if (quantity === "vel") return rotary ? "°/s" : "mm/s";
  return quantity;
}

function axisRows() { return state.hello.twin ? [...AXIS_ROWS, ...TWIN_ROWS] : AXIS_ROWS; }

function buildAxes(hello) {
  const root = $("#axes");
  root.replaceChildren();
  for (const ax of hello.axes) {
    const kv = el("div", { class: "kv" });
    for (const [field, label, , , q] of axisRows()) {
      kv.append(el("span", { text: label }),
        el("span", { class: "v" + (field === "command_position" ? " big" : ""), "data-f": field,
                     "data-unit": unitOf(q, ax.rotary), text: "–" }));
    }
    root.append(el("div", { class: "axis", id: `axis-${ax.axis}` },
      el("h2", {}, el("span", { text: ax.name }), el("small", { text: `axis ${ax.axis}${ax.rotary ? " · rotary" : ""}` })),
      kv, compTable(hello, ax), el("h3", { text: "Temperature compensation (TEMPC)" }), tempcEditor(hello, ax)));
  }
}

function compTable(hello, ax) {
  const head = el("tr", {}, el("th", { text: "compensation" }), el("th", { class: "flag", text: "selected" }),
    el("th", { class: "flag", text: "effective" }), el("th", { class: "num", text: "actual" }), el("th"));
  const body = el("tbody");
  for (const c of hello.comps) {
    // friction's actual value is the drive's additive current, not a length
    const unit = c.key === "FRICT" ? "cur." : unitOf("off", ax.rotary);
    body.append(el("tr", { "data-comp": c.key }, el("td", { text: c.title }),
      el("td", { class: "flag" }, el("span", { class: "dot sel" })),
      el("td", { class: "flag" }, el("span", { class: "dot eff" })),
      el("td", { class: "num act", text: "–" }), el("td", { class: "unit", text: unit })));
  }
  return el("table", { class: "comps" }, el("thead", {}, head), body);
}

function tempcEditor(hello, ax) {
  const root = el("div", { class: "tempc" });
  for (const p of hello.tempc) {
    const boolean = p.type === "BOOLEAN";
    const unit = ax.rotary ? p.rotary_unit : p.unit;  // 0.0001° on a rotary axis, not 0.1 µm
    const input = boolean
      ? el("input", { type: "checkbox", "data-name": p.name, "data-axis": ax.axis })
      : el("input", { type: "text", inputmode: "decimal", "data-name": p.name, "data-axis": ax.axis,
                      title: `${p.name}: ${p.min ?? "–"} … ${p.max ?? "–"} ${unit}; Enter writes` });
    input.addEventListener(boolean ? "change" : "keydown", (ev) => {
      if (boolean || ev.key === "Enter") writeTempc(input, p, ax.axis);
      else if (ev.key === "Escape") { input.classList.remove("pending"); input.blur(); }
    });
    input.addEventListener("input", () => input.classList.add("pending"));
    const label = el("label", { text: p.field });
    if (unit) label.append(" ", el("small", { text: `[${unit}]` }));
    root.append(label, input, el("span", { class: "hint", "data-hint": p.field }));
  }
  root.append(el("span", { class: "msg", id: `tempc-msg-${ax.axis}` }));
  return root;
}

function updateAxes(live) {
  for (const ax of state.axes) {
    const v = live.axes[String(ax.axis)];
    const card = $(`#axis-${ax.axis}`);
    if (!v || !card) continue;
    for (const [field, , lin, rot] of axisRows()) {
      const cell = $(`.v[data-f="${field}"]`, card);
      cell.textContent = `${fmt(v[field], ax.rotary ? rot : lin)} ${cell.dataset.unit}`;
    }
    for (const [key, [sel, eff, act]] of Object.entries(v.comps)) {
      const row = $(`tr[data-comp="${key}"]`, card);
      if (!row) continue;
      $(".sel", row).className = "dot sel" + (sel === null ? " na" : sel ? " on" : "");
      $(".eff", row).className = "dot eff" + (eff === null ? " na" : eff ? " on" : "");
      $(".act", row).textContent = act === null ? "–" : fmt(act, key === "FRICT" ? 0 : ax.rotary ? 4 : 1);
    }
    for (const input of card.querySelectorAll(".tempc input")) {
      const field = input.dataset.name.split("::")[1];
      const hint = $(`.hint[data-hint="${field}"]`, card);
      if (hint) hint.textContent = v.tempc_shown[field] ? `= ${v.tempc_shown[field]}` : "";
      if (document.activeElement === input || input.classList.contains("pending")) continue;
      if (input.type === "checkbox") input.checked = !!v.tempc[field]; else input.value = String(v.tempc[field]);
    }
  }
}

// the server's refusal: an object service error (ADS code) or the HTTP guard's (status)
function refusal(body) {
  if (body.code !== undefined) return `ADS 0x${body.code.toString(16).toUpperCase()}: ${body.message}`;
  return body.status !== undefined ? `HTTP ${body.status}: ${body.message}` : body.message;
}

async function writeTempc(input, p, axis) {
  const msg = $(`#tempc-msg-${axis}`);
  let value;
  if (p.type === "BOOLEAN") value = input.checked;
  else {
    const text = input.value.trim().replace(",", ".");
    value = Number(text);
    if (text === "" || Number.isNaN(value)) {
      msg.className = "msg error"; msg.textContent = `${p.name}: '${input.value}' is not a number`; return;
    }
  }
  msg.className = "msg"; msg.textContent = `writing ${p.name} …`;
  let body;
  try {
    const r = await fetch("api/write", { method: "POST", headers: postHeaders(),
                                          body: JSON.stringify({ name: p.name, axis, value }) });
    body = await r.json();
  } catch (e) {
    body = { ok: false, code: 0x745, message: `no answer from the server (${e})` };
  }
  input.classList.remove("pending");
  if (body.ok) {
    msg.className = "msg ok"; msg.textContent = `${p.name} := ${body.value}`;
  } else {
    msg.className = "msg error"; msg.textContent = refusal(body);
  }
}

// ---------------------------------------------------------------- trends

function chartWidth(host) { return Math.max(360, Math.floor(host.getBoundingClientRect().width) || 400); }

function buildTrends(hello) {
  const root = $("#trends");
  root.replaceChildren();
  const fields = hello.trend_fields, nf = fields.length, tr = hello.trends;
  state.trends = fields.map((f, fi) => {
    const host = el("div");
    root.append(el("div", { class: "trend" },
      el("h3", {}, f.title, " ", el("small", { text: f.unit === f.rotary_unit ? f.unit : `${f.unit} · rotary ${f.rotary_unit}` })), host));
    const data = [tr.t.slice(), ...hello.axes.map((a, i) => tr.series[i * nf + fi].slice())];
    const rot = f.unit !== f.rotary_unit && hello.axes.some((a) => a.rotary);
    const axes = [{ values: clock, space: 70 }, { scale: f.unit, label: f.unit, size: 56, values: ticks }];
    const rotNames = hello.axes.filter((a) => a.rotary).map((a) => a.name).join(" ");
    if (rot) axes.push({ scale: f.rotary_unit, label: `${rotNames} [${f.rotary_unit}]`, side: 1, size: 64,
                           values: ticks, grid: { show: false } });
    const plot = new uPlot({
      width: chartWidth(host), height: 210,
      scales: { x: { time: true } },
      axes,
      series: [{ label: "time" }, ...hello.axes.map((a, i) => ({
        label: a.name, stroke: COLORS[i % COLORS.length], width: 1.5,
        scale: a.rotary && rot ? f.rotary_unit : f.unit,
        value: (u, v) => (v === null ? "–" : v.toFixed(a.rotary && rot ? 4 : 2)),
      }))],
      legend: { live: false },
    }, data, host);
    return { field: f.field, data, plot, host };
  });
}

function pushTrend(live) {
  for (const t of state.trends) {
    t.data[0].push(live.t);
    state.axes.forEach((a, i) => t.data[i + 1].push(live.axes[String(a.axis)][t.field]));
    while (t.data[0].length && t.data[0][0] < live.t - TREND_SECONDS) t.data.forEach((s) => s.shift());
    if (state.pushes % 5 === 0) t.plot.setData(t.data);
  }
}

// ---------------------------------------------------------------- tables

function clampedMarker(t, x) {
  const lo = Math.min(...t.x), hi = Math.max(...t.x);
  return { x: Math.min(hi, Math.max(lo, x)), outside: x < lo || x > hi };
}

function interp(xs, ys, x) {
  if (x <= xs[0]) return ys[0];
  for (let i = 1; i < xs.length; i++) {
    if (x <= xs[i]) return ys[i - 1] + (ys[i] - ys[i - 1]) * (x - xs[i - 1]) / (xs[i] - xs[i - 1]);
  }
  return ys[ys.length - 1];
}

// the position marking a curve: the master's command position, friction's |velocity|
function curvePosition(t) {
  const v = liveAxis(t.x_axis);
  if (!v) return null;
  return t.kind === "frict" ? Math.abs(v.velocity) : v.command_position;
}

// the series the cycle uses now: a bilateral LSEC table by the direction of motion
function activeSeries(t, names) {
  if (names.length < 2) return names[0];
  const v = liveAxis(t.x_axis);
  return v && v.velocity < 0 ? names[1] : names[0];
}

function caption(t) {
  const parts = [];
  const master = (prefix) => {
    const v = liveAxis(t[`${prefix}_axis`]);
    if (!v) return;
    const pos = t.kind === "frict" ? Math.abs(v.velocity) : v.command_position;
    parts.push(el("span", {}, `${t[`${prefix}_name`]} `, el("b", { text: `${fmt(pos, t.kind === "frict" ? 3 : 4)} ${t[`${prefix}_unit`]}` })));
  };
  master("x");
  if (t.y_axis) master("y");
  const own = liveAxis(t.axis);
  if (own && own.comps[t.comp]) {
    const act = own.comps[t.comp][2];
    const unit = t.kind === "frict" ? "" : ` ${unitOf("off", axisInfo(t.axis).rotary)}`;
    parts.push(el("span", {}, `${t.kind === "frict" ? "current" : "applied to " + t.name} `,
      el("b", { text: `${fmt(act, t.kind === "frict" ? 0 : axisInfo(t.axis).rotary ? 4 : 1)}${unit}` })));
  }
  const out = [];
  parts.forEach((p, i) => { if (i) out.push(" · "); out.push(p); });
  return out;
}

function curvePlot(t, host) {
  const names = Object.keys(t.series);
  const state1 = { outside: false };
  const marker = (u) => {
    const pos = curvePosition(t);
    if (pos === null) return;
    const m = clampedMarker(t, pos);
    state1.outside = m.outside;
    const ctx = u.ctx, px = u.valToPos(m.x, "x", true);
    const name = activeSeries(t, names);
    const py = u.valToPos(interp(t.x, t.series[name], m.x), "y", true);
    ctx.save();
    ctx.strokeStyle = m.outside ? "#999" : MARK; ctx.lineWidth = 1.5 * devicePixelRatio;
    ctx.setLineDash([4 * devicePixelRatio, 3 * devicePixelRatio]);
    ctx.beginPath(); ctx.moveTo(px, u.bbox.top); ctx.lineTo(px, u.bbox.top + u.bbox.height); ctx.stroke();
    ctx.setLineDash([]); ctx.beginPath(); ctx.arc(px, py, 4.5 * devicePixelRatio, 0, 2 * Math.PI);
    if (m.outside) { ctx.fillStyle = "#fff"; ctx.fill(); ctx.stroke(); } else { ctx.fillStyle = MARK; ctx.fill(); }
    ctx.restore();
  };
  const x = { time: false };
  const xAxis = { label: `${t.x_name} [${t.x_unit}]`, size: 44, labelSize: 18, values: ticks };
  if (t.kind === "frict") {  // the Stribeck part is near 0: a log-like scale that has 0
    Object.assign(x, { distr: 4, asinh: 0.01, range: (u, lo, hi) => [0, hi * 1.2] });
    xAxis.splits = (u) => [0, 0.01, 0.1, 1, 10, 100, 1000, 10000].filter((v) => v <= u.scales.x.max);
  }
  const plot = new uPlot({
    width: chartWidth(host), height: 210,
    scales: { x },
    axes: [xAxis, { label: t.y_label, size: 56, labelSize: 18, values: ticks }],
    series: [{ label: t.x_unit, value: (u, v) => (v === null ? "–" : `${v}`) },
             ...names.map((n, i) => ({ label: n, stroke: COLORS[i], width: 1.5,
                                       points: { show: t.kind === "frict" } }))],
    hooks: { draw: [marker] },
    legend: { live: false },
  }, [t.x, ...names.map((n) => t.series[n])], host);
  return { plot, outside: () => state1.outside };
}

// ---- heat maps: plane (its grid nodes, bilinear between them) and crosstalk mode 3

const STOPS = [[-1, [33, 102, 172]], [-0.5, [103, 169, 207]], [0, [247, 247, 247]],
               [0.5, [239, 138, 98]], [1, [178, 24, 43]]];

// a value's place on the colour map, −1 … 1: diverging (blue −, white 0, red +) around 0
// when the values have both signs, else light to dark in their own colour
function colorScale(values) {
  const lo = Math.min(...values), hi = Math.max(...values), span = hi - lo || 1;
  if (lo >= 0 && hi > 0) return { f: (v) => 0.12 + 0.88 * (v - lo) / span, lo, hi };
  if (hi <= 0 && lo < 0) return { f: (v) => -0.12 - 0.88 * (hi - v) / span, lo, hi };
  const m = Math.max(-lo, hi) || 1;
  return { f: (v) => v / m, lo: -m, hi: m };
}

function heatColor(f0) {
  const f = Math.min(1, Math.max(-1, f0));
  for (let i = 1; i < STOPS.length; i++) {
    const [f1, c1] = STOPS[i], [f0, c0] = STOPS[i - 1];
    if (f <= f1) { const k = (f - f0) / (f1 - f0); return c0.map((c, j) => Math.round(c + (c1[j] - c) * k)); }
  }
  return STOPS[STOPS.length - 1][1];
}

function niceTicks(lo, hi, count = 5) {
  const span = hi - lo || 1, raw = span / count, mag = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 2.5, 5, 10].map((s) => s * mag).find((s) => span / s <= count) || 10 * mag;
  const out = [];
  for (let v = Math.ceil(lo / step - 1e-9) * step; v <= hi + 1e-9 * span; v += step) out.push(+v.toFixed(10));
  return out;
}

function heatMap(t, canvas) {
  const layers = Object.keys(t.layers);
  const view = { layer: layers[0], bg: null, outside: false };
  const M = { l: 58, r: 78, t: 10, b: 40 };
  const render = () => {  // the map, its axes and colour bar, into an offscreen canvas
    const d = devicePixelRatio, W = canvas.clientWidth, H = canvas.clientHeight;
    const bg = document.createElement("canvas");
    bg.width = canvas.width = Math.round(W * d); bg.height = canvas.height = Math.round(H * d);
    const ctx = bg.getContext("2d"); ctx.scale(d, d);
    const z = t.layers[view.layer], xs = t.x, ys = t.y, nx = xs.length, ny = ys.length;
    const flat = z.flat().concat(t.points ? t.points.layers[view.layer] : []);
    const m = colorScale(flat);
    const g = geometry(t, W, H, M);
    const img = document.createElement("canvas"); img.width = nx; img.height = ny;
    const ic = img.getContext("2d"), id = ic.createImageData(nx, ny);
    for (let j = 0; j < ny; j++) for (let i = 0; i < nx; i++) {
      const [r, gg, b] = heatColor(m.f(z[j][i])), k = 4 * ((ny - 1 - j) * nx + i);
      id.data[k] = r; id.data[k + 1] = gg; id.data[k + 2] = b; id.data[k + 3] = 255;
    }
    ic.putImageData(id, 0, 0);
    const cw = (g.px(xs[nx - 1]) - g.px(xs[0])) / Math.max(1, nx - 1);
    const ch = (g.py(ys[0]) - g.py(ys[ny - 1])) / Math.max(1, ny - 1);
    ctx.save(); ctx.beginPath(); ctx.rect(g.x0, g.y1, g.x1 - g.x0, g.y0 - g.y1); ctx.clip();
    ctx.imageSmoothingEnabled = true;  // bilinear between the nodes, as the cycle does
    ctx.drawImage(img, g.px(xs[0]) - cw / 2, g.py(ys[ny - 1]) - ch / 2, nx * cw, ny * ch);
    ctx.restore();
    if (t.points) drawPoints(ctx, t, g, m, view.layer);
    drawFrame(ctx, t, g);
    drawColorBar(ctx, g, m, t.z_unit, H);
    view.bg = bg;
  };
  const redraw = () => {
    if (!view.bg || view.bg.width !== Math.round(canvas.clientWidth * devicePixelRatio)) render();
    const ctx = canvas.getContext("2d");
    ctx.setTransform(1, 0, 0, 1, 0, 0); ctx.clearRect(0, 0, canvas.width, canvas.height);
    ctx.drawImage(view.bg, 0, 0);
    ctx.scale(devicePixelRatio, devicePixelRatio);
    view.outside = drawHeatMarker(ctx, t, geometry(t, canvas.clientWidth, canvas.clientHeight, M));
  };
  const setLayer = (name) => { view.layer = name; view.bg = null; redraw(); };
  return { redraw, setLayer, layers, outside: () => view.outside, invalidate: () => { view.bg = null; } };
}

function geometry(t, W, H, M) {
  const xlo = Math.min(...t.x), xhi = Math.max(...t.x), ylo = Math.min(...t.y), yhi = Math.max(...t.y);
  const x0 = M.l, x1 = W - M.r, y0 = H - M.b, y1 = M.t;
  return { x0, x1, y0, y1, xlo, xhi, ylo, yhi,
           px: (x) => x0 + (x - xlo) / ((xhi - xlo) || 1) * (x1 - x0),
           py: (y) => y0 - (y - ylo) / ((yhi - ylo) || 1) * (y0 - y1) };
}

function drawPoints(ctx, t, g, m, layer) {
  const p = t.points;
  p.x.forEach((x, i) => {
    const [r, gg, b] = heatColor(m.f(p.layers[layer][i]));
    ctx.fillStyle = `rgb(${r},${gg},${b})`; ctx.strokeStyle = "#1d2733"; ctx.lineWidth = 1;
    ctx.beginPath(); ctx.arc(g.px(x), g.py(p.y[i]), 4, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
  });
}

function drawFrame(ctx, t, g) {
  ctx.strokeStyle = "#9aa5b1"; ctx.lineWidth = 1; ctx.strokeRect(g.x0, g.y1, g.x1 - g.x0, g.y0 - g.y1);
  ctx.fillStyle = "#1d2733"; ctx.font = "11px system-ui, sans-serif";
  ctx.textAlign = "center"; ctx.textBaseline = "top";
  for (const v of niceTicks(g.xlo, g.xhi)) {
    const x = g.px(v);
    ctx.fillRect(x, g.y0, 1, 4); ctx.fillText(String(v), x, g.y0 + 6);
  }
  ctx.font = "bold 11px system-ui, sans-serif";
  ctx.fillText(`${t.x_name} [${t.x_unit}]`, (g.x0 + g.x1) / 2, g.y0 + 22);
  ctx.font = "11px system-ui, sans-serif"; ctx.textAlign = "right"; ctx.textBaseline = "middle";
  for (const v of niceTicks(g.ylo, g.yhi)) {
    const y = g.py(v);
    ctx.fillRect(g.x0 - 4, y, 4, 1); ctx.fillText(String(v), g.x0 - 6, y);
  }
  ctx.save(); ctx.translate(12, (g.y0 + g.y1) / 2); ctx.rotate(-Math.PI / 2);
  ctx.textAlign = "center"; ctx.font = "bold 11px system-ui, sans-serif";
  ctx.fillText(`${t.y_name} [${t.y_unit}]`, 0, 0); ctx.restore();
}

function drawColorBar(ctx, g, m, unit, H) {
  const x = g.x1 + 14, w = 12, top = g.y1, bottom = g.y0;
  for (let y = top; y < bottom; y++) {
    const [r, gg, b] = heatColor(m.f(m.hi - (m.hi - m.lo) * (y - top) / (bottom - top)));
    ctx.fillStyle = `rgb(${r},${gg},${b})`; ctx.fillRect(x, y, w, 1);
  }
  ctx.strokeStyle = "#9aa5b1"; ctx.strokeRect(x, top, w, bottom - top);
  ctx.fillStyle = "#1d2733"; ctx.font = "11px system-ui, sans-serif"; ctx.textAlign = "left";
  ctx.textBaseline = "middle";
  const big = Math.max(Math.abs(m.lo), Math.abs(m.hi));
  const digits = big >= 10 ? 0 : big >= 1 ? 1 : big >= 0.01 ? 3 : 5;
  [[m.hi, top], [(m.lo + m.hi) / 2, (top + bottom) / 2], [m.lo, bottom]]
    .forEach(([v, y]) => ctx.fillText(v.toFixed(digits), x + w + 4, y));
  ctx.textBaseline = "top"; ctx.fillText(unit, x, Math.min(H - 14, bottom + 8));
}

function drawHeatMarker(ctx, t, g) {
  const vx = liveAxis(t.x_axis), vy = liveAxis(t.y_axis);
  if (!vx || !vy) return false;
  const mx = vx.command_position, my = vy.command_position;
  const outside = mx < g.xlo || mx > g.xhi || my < g.ylo || my > g.yhi;
  const cx = g.px(Math.min(g.xhi, Math.max(g.xlo, mx))), cy = g.py(Math.min(g.yhi, Math.max(g.ylo, my)));
  ctx.save();
  ctx.strokeStyle = "rgba(29,39,51,0.45)"; ctx.setLineDash([3, 3]); ctx.lineWidth = 1;
  ctx.beginPath(); ctx.moveTo(cx, g.y1); ctx.lineTo(cx, g.y0); ctx.moveTo(g.x0, cy); ctx.lineTo(g.x1, cy); ctx.stroke();
  ctx.setLineDash([]);
  ctx.lineWidth = 4; ctx.strokeStyle = "#fff"; ctx.beginPath(); ctx.arc(cx, cy, 7, 0, 2 * Math.PI); ctx.stroke();
  ctx.lineWidth = 2; ctx.strokeStyle = outside ? "#888" : "#111"; ctx.beginPath(); ctx.arc(cx, cy, 7, 0, 2 * Math.PI); ctx.stroke();
  if (!outside) { ctx.fillStyle = "#111"; ctx.beginPath(); ctx.arc(cx, cy, 2.5, 0, 2 * Math.PI); ctx.fill(); }
  ctx.restore();
  return outside;
}

async function buildTables() {
  const r = await fetch("api/tables");
  state.tables = await r.json();
  const root = $("#tables");
  root.replaceChildren();
  state.tablePlots = state.tables.map((t) => {
    const title = el("h3", { text: t.title });
    const cap = el("div", { class: "caption" });
    const card = el("div", { class: "table-card", "data-kind": t.kind, "data-axis": t.axis }, title);
    root.append(card);
    let view;
    if (t.layers) {
      const canvas = el("canvas", { class: "heat" });
      card.append(canvas, cap);
      view = heatMap(t, canvas);
      if (view.layers.length > 1) {
        const sel = el("select", { "aria-label": "correction column" },
          ...view.layers.map((n) => el("option", { value: n, text: n })));
        sel.addEventListener("change", () => view.setLayer(sel.value));
        title.append(sel);
      }
    } else {
      const host = el("div");
      card.append(host, cap);
      const c = curvePlot(t, host);
      view = { redraw: () => c.plot.redraw(false), outside: c.outside, plot: c.plot, host };
    }
    const redraw = () => {
      view.redraw();
      const kids = caption(t);
      if (view.outside()) kids.push(" · ", el("span", { class: "outside", text: "outside the table" }));
      cap.replaceChildren(...kids);
    };
    return { t, view, redraw };
  });
  state.tablePlots.forEach((p) => p.redraw());
}

// ---------------------------------------------------------------- status, errors

function showStatus(st) {
  const s = $("#status");
  s.classList.toggle("stalled", !!st.stalled);
  s.textContent = st.stalled
    ? `STALLED: no GEO cycle for ${st.stalled_for_s} s`
    : `cycle ${st.cycle} · ${st.engine} engine · overruns ${st.overruns}`;
  const faults = st.faults || [];
  const banner = $("#faults");
  banner.hidden = faults.length === 0;
  banner.textContent = faults.length
    ? "Injected faults: " + faults.map((f) => `#${f.id} ${f.fault} (${f.hits} hits)`).join(" · ")
    : "";
}

function addError(e, top = true) {
  const body = $("#errors tbody");
  $(".empty", body)?.remove();
  const where = e.file && e.line ? `${e.file}:${e.line}: ` : "";
  const row = el("tr", { class: e.severity || "" },
    el("td", { text: e.cycle ?? "" }), el("td", { text: e.severity || "" }),
    el("td", { text: e.error_id || "" }), el("td", { text: e.axis ? axisInfo(e.axis).name : "" }),
    el("td", { text: where + e.message }));
  if (top) body.prepend(row); else body.append(row);
  while (body.children.length > 100) body.lastChild.remove();
}

function showErrors(errors) {
  const body = $("#errors tbody");
  body.replaceChildren();
  if (!errors.length) body.append(el("tr", { class: "empty" }, el("td", { colspan: 5, text: "none" })));
  errors.slice().reverse().forEach((e) => addError(e, false));
}

async function command(name) {
  const msg = $("#command-result");
  msg.className = "msg"; msg.textContent = `${name} …`;
  let body;
  try {
    body = await (await fetch(`api/command/${name}`, { method: "POST", headers: postHeaders(), body: "{}" })).json();
  } catch (e) {
    body = { ok: false, message: `no answer from the server (${e})` };
  }
  if (body.ok) {
    msg.className = "msg";
    msg.textContent = name === "save"
      ? (body.files.length ? `saved: ${body.files.join(", ")}` : "saved: nothing had changed")
      : `reloaded (${body.files.length} files)`;
    if (name === "reload") buildTables();
  } else {
    msg.className = "msg error";
    msg.textContent = `${name} failed: ${(body.errors || []).join("; ") || refusal(body)}`;
  }
  msg.title = msg.textContent;
}

// ---------------------------------------------------------------- the socket

function onMessage(m) {
  if (m.type === "hello") {
    state.hello = m; state.axes = m.axes; state.live = null;
    $("#machine").textContent = `${m.machine} · ${m.version}`;
    $("#fleet-link").hidden = !m.fleet;
    document.title = `geo-server HMI · ${m.machine}`;
    buildAxes(m); buildTrends(m); buildTables(); showStatus(m.status); showErrors(m.errors);
    if (m.read_only) {  // geo-server run --read-only: the server refuses edits and commands
      document.querySelectorAll("input[data-name], #reload, #save").forEach((e) => { e.disabled = true; });
      $("#command-result").textContent = "read-only server";
    }
  } else if (m.type === "live") {
    state.live = m; state.pushes += 1;
    updateAxes(m); pushTrend(m);
    state.tablePlots.forEach((p) => p.redraw());
    document.body.dataset.cycle = m.cycle;
  } else if (m.type === "status") {
    showStatus(m.status);
  } else if (m.type === "error") {
    addError(m.error);
  } else if (m.type === "tables") {
    buildTables();
  } else if (m.type === "stalled") {
    $("#status").textContent = `STALLED: ${m.message}`; $("#status").classList.add("stalled");
  }
}

function connect() {
  // relative to the page: /ws for one machine, /m/<name>/ws for a machine of a fleet
  const url = new URL("ws", location.href);
  url.protocol = location.protocol === "https:" ? "wss:" : "ws:";
  const ws = new WebSocket(url);
  ws.onmessage = (ev) => onMessage(JSON.parse(ev.data));
  ws.onclose = () => { $("#status").textContent = "disconnected; reconnecting…"; setTimeout(connect, 1000); };
}

function resize() {
  for (const t of state.trends) t.plot.setSize({ width: chartWidth(t.host), height: 210 });
  for (const p of state.tablePlots) {
    if (p.view.plot) p.view.plot.setSize({ width: chartWidth(p.view.host), height: 210 });
    if (p.view.invalidate) p.view.invalidate();
    p.redraw();
  }
}

let resizing = null;
window.addEventListener("resize", () => { clearTimeout(resizing); resizing = setTimeout(resize, 150); });
$("#reload").addEventListener("click", () => command("reload"));
$("#save").addEventListener("click", () => command("save"));
connect();
