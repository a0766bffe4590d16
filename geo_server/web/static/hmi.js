// geo-server web HMI (docs/web.md): one WebSocket, pushes 10 times a second.
"use strict";

const COLORS = ["#0b6bcb", "#d9480f", "#2b8a3e", "#862e9c", "#e67700", "#c2255c"];
const TREND_MAX = 6000;
const state = { hello: null, axes: [], charts: {}, trend: null, tables: [], tablePlots: [],
                live: null, pushes: 0 };

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

// ---------------------------------------------------------------- axis cards

const AXIS_ROWS = [
  ["command_position", "command position", 4, "pos"],
  ["output_position", "output position", 4, "pos"],
  ["total_offset", "total offset", 1, "off"],
  ["velocity", "velocity", 3, "vel"],
  ["residual", "residual error (twin)", 2, "off"],
  ["sensor_temperature", "sensor (twin)", 2, "°C"],
];

function unitOf(kind, rotary) {
  if (kind === "pos") return rotary ? "°" : "mm";
  if (kind === "off") return rotary ? "°" : "µm";
  if (kind === "vel") return rotary ? "°/s" : "mm/s";
  return kind;
}

function buildAxes(hello) {
  const root = $("#axes");
  root.replaceChildren();
  for (const ax of hello.axes) {
    const kv = el("div", { class: "kv" });
    for (const [field, label, , kind] of AXIS_ROWS) {
      kv.append(el("span", { text: label }),
        el("span", { class: "v", "data-f": field, "data-unit": unitOf(kind, ax.rotary), text: "–" }));
    }
    const comps = el("table", { class: "comps" },
      el("thead", {}, el("tr", {}, el("th", { text: "compensation" }), el("th", { text: "selected" }),
        el("th", { text: "effective" }), el("th", { text: `actual (${ax.rotary ? "°" : "µm"})` }))));
    const body = el("tbody");
    for (const c of hello.comps) {
      // friction's actual value is the drive's additive current, not a length
      const title = c.key === "FRICT" ? `${c.title} (current)` : c.title;
      body.append(el("tr", { "data-comp": c.key }, el("td", { text: title }),
        el("td", {}, el("span", { class: "dot sel" })), el("td", {}, el("span", { class: "dot eff" })),
        el("td", { class: "num act", text: "–" })));
    }
    comps.append(body);
    const tempc = el("div", { class: "tempc" });
    for (const p of hello.tempc) {
      const input = p.type === "BOOLEAN"
        ? el("input", { type: "checkbox", "data-name": p.name, "data-axis": ax.axis })
        : el("input", { type: "text", inputmode: "decimal", "data-name": p.name, "data-axis": ax.axis,
                        title: `${p.name} [${p.unit}] ${p.min ?? ""} … ${p.max ?? ""}` });
      input.addEventListener(p.type === "BOOLEAN" ? "change" : "keydown", (ev) => {
        if (p.type === "BOOLEAN" || ev.key === "Enter") writeTempc(input, p, ax.axis);
      });
      input.addEventListener("input", () => input.classList.add("pending"));
      tempc.append(el("label", { text: `${p.field}${p.unit ? " [" + p.unit + "]" : ""}` }), input);
    }
    tempc.append(el("span", { class: "msg", id: `tempc-msg-${ax.axis}` }));
    root.append(el("div", { class: "axis", id: `axis-${ax.axis}` },
      el("h2", {}, el("span", { text: ax.name }), el("small", { text: `axis ${ax.axis}${ax.rotary ? " · rotary" : ""}` })),
      kv, comps, el("h3", { text: "Temperature compensation (TEMPC)" }), tempc));
  }
}

function updateAxes(live) {
  for (const ax of state.axes) {
    const v = live.axes[String(ax.axis)];
    const card = $(`#axis-${ax.axis}`);
    if (!v || !card) continue;
    for (const [field, , digits] of AXIS_ROWS) {
      const cell = $(`.v[data-f="${field}"]`, card);
      cell.textContent = `${fmt(v[field], ax.rotary && digits < 4 && field !== "sensor_temperature" ? 4 : digits)} ${cell.dataset.unit}`;
    }
    for (const [key, [sel, eff, act]] of Object.entries(v.comps)) {
      const row = $(`tr[data-comp="${key}"]`, card);
      if (!row) continue;
      $(".sel", row).className = "dot sel" + (sel === null ? " na" : sel ? " on" : "");
      $(".eff", row).className = "dot eff" + (eff === null ? " na" : eff ? " on" : "");
      $(".act", row).textContent = act === null ? "–" : fmt(act, ax.rotary ? 4 : 1);
    }
    for (const input of card.querySelectorAll(".tempc input")) {
      if (document.activeElement === input || input.classList.contains("pending")) continue;
      const value = v.tempc[input.dataset.name.split("::")[1]];
      if (input.type === "checkbox") input.checked = !!value; else input.value = String(value);
    }
  }
}

async function writeTempc(input, p, axis) {
  const msg = $(`#tempc-msg-${axis}`);
  let value;
  if (p.type === "BOOLEAN") value = input.checked;
  else {
    value = Number(input.value.trim().replace(",", "."));
    if (input.value.trim() === "" || Number.isNaN(value)) {
      msg.className = "msg error"; msg.textContent = `${p.name}: '${input.value}' is not a number`; return;
    }
  }
  msg.className = "msg"; msg.textContent = `writing ${p.name} …`;
  const r = await fetch("/api/write", { method: "POST", headers: { "Content-Type": "application/json" },
                                        body: JSON.stringify({ name: p.name, axis, value }) });
  const body = await r.json();
  input.classList.remove("pending");
  if (body.ok) {
    msg.className = "msg ok"; msg.textContent = `${p.name} := ${body.value}`;
  } else {
    msg.className = "msg error"; msg.textContent = `ADS 0x${body.code.toString(16).toUpperCase()}: ${body.message}`;
  }
}

// ---------------------------------------------------------------- trends

function buildTrends(hello) {
  const fields = hello.trend_fields;
  const n = hello.axes.length;
  state.trend = fields.map(() => [[], ...hello.axes.map(() => [])]);
  const tr = hello.trends;
  tr.t.forEach((t, k) => {
    fields.forEach((_, fi) => {
      state.trend[fi][0].push(t);
      for (let a = 0; a < n; a++) state.trend[fi][a + 1].push(tr.series[a * fields.length + fi][k]);
    });
  });
  fields.forEach((f, fi) => {
    const host = $(`#trend-${f}`);
    host.replaceChildren();
    const opts = {
      width: Math.max(380, host.clientWidth || 400), height: 180,
      scales: { x: { time: false } },
      axes: [{ label: "s" }, {}],
      series: [{ label: "t [s]" }, ...hello.axes.map((a, i) => ({ label: a.name, stroke: COLORS[i % COLORS.length], width: 1.5 }))],
      legend: { live: false },
    };
    state.charts[f] = new uPlot(opts, state.trend[fi], host);
  });
}

function pushTrend(live) {
  const fields = state.hello.trend_fields;
  fields.forEach((f, fi) => {
    const d = state.trend[fi];
    d[0].push(live.t);
    state.axes.forEach((a, i) => d[i + 1].push(live.axes[String(a.axis)][f]));
    if (d[0].length > TREND_MAX) d.forEach((s) => s.shift());
  });
  if (state.pushes % 5 === 0) fields.forEach((f, fi) => state.charts[f].setData(state.trend[fi]));
}

// ---------------------------------------------------------------- tables

function positionOf(axis) {
  const live = state.live;
  if (!live || !live.axes[String(axis)]) return null;
  return live.axes[String(axis)].command_position;
}

function curvePlot(t, host) {
  const names = Object.keys(t.series);
  const marker = (u) => {
    const x = positionOf(t.x_axis);
    if (x === null || t.kind === "frict") return;
    const ctx = u.ctx, px = u.valToPos(x, "x", true);
    if (px < u.bbox.left || px > u.bbox.left + u.bbox.width) return;
    ctx.save(); ctx.strokeStyle = "#c62828"; ctx.lineWidth = 1.5; ctx.setLineDash([4, 3]);
    ctx.beginPath(); ctx.moveTo(px, u.bbox.top); ctx.lineTo(px, u.bbox.top + u.bbox.height); ctx.stroke();
    const y = interp(t.x, t.series[names[0]], x);
    ctx.setLineDash([]); ctx.fillStyle = "#c62828"; ctx.beginPath();
    ctx.arc(px, u.valToPos(y, "y", true), 4 * devicePixelRatio, 0, 2 * Math.PI); ctx.fill(); ctx.restore();
  };
  return new uPlot({
    width: Math.max(380, host.clientWidth || 400), height: 200,
    scales: { x: { time: false } },
    axes: [{ label: t.x_unit }, { label: t.y_unit }],
    series: [{ label: t.x_unit }, ...names.map((n, i) => ({ label: n, stroke: COLORS[i], width: 1.5 }))],
    hooks: { draw: [marker] },
    legend: { live: false },
  }, [t.x, ...names.map((n) => t.series[n])], host);
}

function interp(xs, ys, x) {
  if (x <= xs[0]) return ys[0];
  for (let i = 1; i < xs.length; i++) {
    if (x <= xs[i]) return ys[i - 1] + (ys[i] - ys[i - 1]) * (x - xs[i - 1]) / (xs[i] - xs[i - 1]);
  }
  return ys[ys.length - 1];
}

function heatColor(v, lo, hi) {
  const f = hi > lo ? (v - lo) / (hi - lo) : 0.5;
  const h = 240 - 240 * Math.min(1, Math.max(0, f));  // blue (low) … red (high)
  return `hsl(${h}, 75%, 50%)`;
}

function heatPlot(t, canvas) {
  const w = canvas.width = 400 * devicePixelRatio, h = canvas.height = 260 * devicePixelRatio;
  const ctx = canvas.getContext("2d"), pad = 30 * devicePixelRatio;
  const xs = t.x, ys = t.y;
  const flat = t.kind === "plane" ? t.z.flat() : t.z;
  const lo = Math.min(...flat), hi = Math.max(...flat);
  const x0 = Math.min(...xs), x1 = Math.max(...xs), y0 = Math.min(...ys), y1 = Math.max(...ys);
  const px = (x) => pad + (x - x0) / ((x1 - x0) || 1) * (w - 2 * pad);
  const py = (y) => h - pad - (y - y0) / ((y1 - y0) || 1) * (h - 2 * pad);
  ctx.clearRect(0, 0, w, h);
  if (t.kind === "plane") {
    const cw = (w - 2 * pad) / Math.max(1, xs.length - 1), ch = (h - 2 * pad) / Math.max(1, ys.length - 1);
    t.z.forEach((row, j) => row.forEach((v, i) => {
      ctx.fillStyle = heatColor(v, lo, hi); ctx.fillRect(px(xs[i]) - cw / 2, py(ys[j]) - ch / 2, cw + 1, ch + 1);
    }));
  } else {
    xs.forEach((x, i) => { ctx.fillStyle = heatColor(flat[i], lo, hi); ctx.beginPath();
      ctx.arc(px(x), py(ys[i]), 9 * devicePixelRatio, 0, 2 * Math.PI); ctx.fill(); });
  }
  ctx.fillStyle = "#1d2733"; ctx.font = `${11 * devicePixelRatio}px system-ui`;
  ctx.fillText(`${x0} … ${x1} ${t.x_unit}`, pad, h - 8 * devicePixelRatio);
  ctx.save(); ctx.translate(12 * devicePixelRatio, h - pad); ctx.rotate(-Math.PI / 2);
  ctx.fillText(`${y0} … ${y1} ${t.x_unit}`, 0, 0); ctx.restore();
  const mx = positionOf(t.x_axis), my = positionOf(t.y_axis);
  if (mx !== null && my !== null) {
    const cx = px(Math.min(x1, Math.max(x0, mx))), cy = py(Math.min(y1, Math.max(y0, my)));
    ctx.strokeStyle = "#fff"; ctx.lineWidth = 3 * devicePixelRatio;
    ctx.beginPath(); ctx.arc(cx, cy, 6 * devicePixelRatio, 0, 2 * Math.PI); ctx.stroke();
    ctx.fillStyle = "#111"; ctx.beginPath(); ctx.arc(cx, cy, 4 * devicePixelRatio, 0, 2 * Math.PI); ctx.fill();
  }
  return `${t.z_unit}: ${lo} (blue) … ${hi} (red)`;
}

async function buildTables() {
  const r = await fetch("/api/tables");
  state.tables = await r.json();
  const root = $("#tables");
  root.replaceChildren();
  state.tablePlots = state.tables.map((t) => {
    const card = el("div", { class: "table-card", "data-kind": t.kind, "data-axis": t.axis },
      el("h3", { text: t.title }));
    root.append(card);
    if (t.kind === "plane" || t.kind === "scatter") {
      const canvas = el("canvas", { class: "heat" });
      const legend = el("div", { class: "legend" });
      card.append(canvas, legend);
      return { t, redraw: () => { legend.textContent = heatPlot(t, canvas); } };
    }
    const host = el("div");
    card.append(host);
    const plot = curvePlot(t, host);
    return { t, redraw: () => plot.redraw(false) };
  });
  state.tablePlots.forEach((p) => p.redraw());
}

// ---------------------------------------------------------------- status, errors

function showStatus(st) {
  const s = $("#status");
  s.classList.toggle("stalled", !!st.stalled);
  s.textContent = st.stalled
    ? `STALLED: no GEO cycle for ${st.stalled_for_s} s`
    : `cycle ${st.cycle} · ${st.engine} · overruns ${st.overruns}`;
  const faults = st.faults || [];
  const banner = $("#faults");
  banner.hidden = faults.length === 0;
  banner.textContent = faults.length
    ? "Injected faults: " + faults.map((f) => `#${f.id} ${f.fault} (${f.hits} hits)`).join(" · ")
    : "";
}

function addError(e, top = true) {
  const body = $("#errors tbody");
  const row = el("tr", { class: e.severity || "" },
    el("td", { text: e.cycle ?? "" }), el("td", { text: e.severity || "" }),
    el("td", { text: e.error_id || "" }),
    el("td", { text: (e.file && e.line ? `${e.file}:${e.line}: ` : "") + e.message }));
  if (top) body.prepend(row); else body.append(row);
  while (body.children.length > 100) body.lastChild.remove();
}

async function command(name) {
  const msg = $("#command-result");
  msg.className = "msg"; msg.textContent = `${name} …`;
  const r = await fetch(`/api/command/${name}`, { method: "POST" });
  const body = await r.json();
  if (body.ok) {
    msg.className = "msg";
    msg.textContent = name === "save"
      ? (body.files.length ? `saved: ${body.files.join(", ")}` : "saved: nothing had changed")
      : `reloaded (${body.files.length} files)`;
  } else {
    msg.className = "msg error";
    msg.textContent = `${name} failed: ${(body.errors || []).join("; ") || body.message}`;
  }
}

// ---------------------------------------------------------------- the socket

function connect() {
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  ws.onmessage = (ev) => {
    const m = JSON.parse(ev.data);
    if (m.type === "hello") {
      state.hello = m; state.axes = m.axes;
      $("#machine").textContent = `${m.machine} · ${m.version}`;
      document.title = `geo-server HMI · ${m.machine}`;
      buildAxes(m); buildTrends(m); buildTables(); showStatus(m.status);
      $("#errors tbody").replaceChildren();
      m.errors.slice().reverse().forEach((e) => addError(e, false));
    } else if (m.type === "live") {
      state.live = m; state.pushes += 1;
      updateAxes(m); pushTrend(m);
      if (state.pushes % 2 === 0) state.tablePlots.forEach((p) => p.redraw());
      document.body.dataset.cycle = m.cycle;
    } else if (m.type === "status") {
      showStatus(m.status);
    } else if (m.type === "error") {
      addError(m.error);
    } else if (m.type === "stalled") {
      $("#status").textContent = m.message; $("#status").classList.add("stalled");
    }
  };
  ws.onclose = () => { $("#status").textContent = "disconnected; reconnecting…"; setTimeout(connect, 1000); };
}

$("#reload").addEventListener("click", () => command("reload"));
$("#save").addEventListener("click", () => command("save"));
connect();
