// The page of dmosim view: draws each page the server pushes (Server-Sent Events, /events) with plain SVG, canvas
// and tables; nothing is loaded from anywhere but this server. The server aggregates (dmosim/view/page.py).
"use strict";

const $ = (id) => document.getElementById(id);
const SVG = "http://www.w3.org/2000/svg";
const HOURS = 24;
let last = null;

function fmt(x, digits = 2) {
  return x === null || x === undefined ? "" : Number(x).toLocaleString("en-US", {
    minimumFractionDigits: digits, maximumFractionDigits: digits });
}

function el(tag, attrs = {}, text) {
  const e = tag.startsWith("svg:") ? document.createElementNS(SVG, tag.slice(4)) : document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (text !== undefined) e.textContent = text;
  return e;
}

// A colour from blue (low) through white to red (high), for a value in [lo, hi].
function diverging(v, lo, hi) {
  if (v === null || v === undefined) return "#ddd";
  const mid = (lo + hi) / 2, half = Math.max((hi - lo) / 2, 1e-9);
  const t = Math.max(-1, Math.min(1, (v - mid) / half));
  const a = Math.round(255 * (1 - 0.7 * Math.abs(t)));  // at most 70%: the numbers on it stay legible
  return t >= 0 ? `rgb(255,${a},${a})` : `rgb(${a},${a},255)`;
}
function sequential(v, hi) {
  if (v === null || v === undefined) return "#ddd";
  const t = hi > 0 ? Math.max(0, Math.min(1, v / hi)) : 0;
  const a = Math.round(255 * (1 - 0.85 * t));
  return `rgb(255,${a},${a})`;
}

// Lines over the 24 hours in an SVG of viewBox w x h, with a y axis of a few ticks.
function lines(svg, series, opts = {}) {
  svg.replaceChildren();
  const [w, h] = [720, 200], left = 44, bottom = 18, top = 6;
  const values = series.flatMap((s) => s.values.filter((v) => v !== null && v !== undefined));
  if (!values.length) return;
  let lo = Math.min(...values), hi = Math.max(...values);
  if (hi - lo < 1e-9) { lo -= 1; hi += 1; }
  const x = (i) => left + (i + 0.5) * (w - left - 4) / HOURS;
  const y = (v) => top + (hi - v) / (hi - lo) * (h - top - bottom);
  for (let k = 0; k <= 4; k++) {
    const v = lo + (hi - lo) * k / 4;
    svg.append(el("svg:line", { x1: left, x2: w, y1: y(v), y2: y(v), stroke: "#eee" }));
    svg.append(el("svg:text", { x: left - 4, y: y(v) + 4, "text-anchor": "end", "font-size": 10, fill: "#777" },
      fmt(v, hi - lo < 10 ? 1 : 0)));
  }
  for (let i = 0; i < HOURS; i += 3)
    svg.append(el("svg:text", { x: x(i), y: h - 4, "text-anchor": "middle", "font-size": 10, fill: "#777" }, i + 1));
  if (opts.now) svg.append(el("svg:rect", { x: x(opts.now - 1) - 6, y: top, width: 12, height: h - top - bottom,
    fill: "#f39c12", opacity: 0.15 }));
  series.forEach((s) => {
    let d = "";
    s.values.forEach((v, i) => { if (v !== null && v !== undefined) d += `${d ? "L" : "M"}${x(i)},${y(v)}`; });
    svg.append(el("svg:path", { d, fill: "none", stroke: s.color, "stroke-width": 2, "stroke-dasharray": s.dash || "" }));
  });
  let lx = left + 6;
  series.forEach((s) => {
    svg.append(el("svg:rect", { x: lx, y: top + 2, width: 10, height: 3, fill: s.color }));
    const t = el("svg:text", { x: lx + 14, y: top + 8, "font-size": 10, fill: "#333" }, s.name);
    svg.append(t); lx += 14 + 6.5 * s.name.length + 12;
  });
}

function drawClock(p) {
  const c = p.clock;
  $("mode").textContent = p.mode === "replay" ? "replay of" : "live:";
  $("run-id").textContent = p.run_id || "";
  $("market-day").textContent = p.market_day || "-";
  $("phase").textContent = c ? c.phase : "waiting for the DMO";
  $("hour").textContent = c && c.hour ? `${c.hour}/24` : "-";
  $("day-of").textContent = c ? `${c.day}/${c.days}` : "-";
  document.body.dataset.phase = c ? c.phase : "";
  document.body.dataset.hour = c && c.hour ? c.hour : "";
  document.body.dataset.settled = p.summary ? "yes" : "no";
  const waiting = p.waiting_count ? `the DMO waits for ${p.waiting_for.join(", ")}` +
    (p.waiting_count > p.waiting_for.length ? ` and ${p.waiting_count - p.waiting_for.length} more` : "") : "";
  $("waiting").textContent = waiting;
  $("messages").textContent = p.messages;
  $("present").textContent = p.present ? `present: ${p.present.length} process(es)` : "";
  $("dropped").textContent = p.dropped ? `· ${p.dropped} messages dropped by the observer` : "";
}

function drawControls(p) {
  if (p.mode !== "replay") return;
  $("controls").hidden = false;
  $("play").textContent = p.ended ? "ended" : p.paused ? "play" : "pause";
  $("play").dataset.paused = p.paused ? "yes" : "no";
  const rate = $("rate");
  if (document.activeElement !== rate) {
    if (![...rate.options].some((o) => Number(o.value) === p.rate)) rate.append(el("option", {}, String(p.rate)));
    rate.value = [...rate.options].find((o) => Number(o.value) === p.rate).value;
  }
  const slider = $("slider");
  slider.max = Math.max(0, p.marks.length - 1);
  if (document.activeElement !== slider && p.mark !== null) slider.value = p.mark;
  $("mark-label").textContent = p.mark !== null ? p.marks[p.mark] : "";
  document.body.dataset.ended = p.ended ? "yes" : "no";
}

function drawPrices(p) {
  const h = p.hours;
  if (!h) return;
  const series = [{ name: "ISO price", values: h.iso, color: "#7f8c8d", dash: "4 3" }];
  const differ = h.clearing_low.some((v, i) => v !== h.clearing_high[i]);
  if (differ) {
    series.push({ name: "lowest bus price", values: h.clearing_low, color: "#2980b9" });
    series.push({ name: "highest bus price", values: h.clearing_high, color: "#c0392b" });
  } else series.push({ name: "clearing price", values: h.clearing_low, color: "#2980b9" });
  lines($("prices"), series, { now: p.clock && p.clock.hour });
  const strip = $("congestion");
  strip.replaceChildren();
  h.congestion.forEach((c, i) => strip.append(el("span", { class: c && c !== "none" ? "c" : "",
    title: `hour ${i + 1}: ${c || "unknown"}` }, c && c !== "none" ? c : "·")));
}

function drawAwards(p) {
  const table = $("awards");
  $("awards-wrap").hidden = !!p.compact;
  $("compact").hidden = !p.compact;
  if (p.compact) { drawCompact(p.compact); return; }
  table.replaceChildren();
  const head = el("tr");
  head.append(el("th", {}, "agent"), el("th", {}, "bus"));
  for (let i = 1; i <= HOURS; i++) head.append(el("th", {}, i));
  table.append(head);
  const now = p.clock && p.clock.hour;
  for (const a of p.detail) {
    const row = el("tr", { "data-agent": a.agent });
    row.append(el("th", {}, a.agent), el("td", {}, a.bus || ""));
    for (let i = 0; i < HOURS; i++) {
      const award = a.award ? a.award[i] : null, metered = a.import[i];
      const cell = el("td", { class: "h" + (metered !== null && award !== null && metered > award + 1e-6 ? " over" : "")
        + (now === i + 1 ? " now" : ""), "data-hour": i + 1, "data-agent": a.agent,
        title: `${a.agent} hour ${i + 1}: award ${fmt(award, 3)} MW, metered ${fmt(metered, 3)} MWh` +
               (a.price ? `, price ${fmt(a.price[i])} $/MWh` : "") });
      if (award !== null) cell.dataset.award = award;
      if (metered !== null) cell.dataset.import = metered;
      cell.append(el("span", { class: "a" }, fmt(award, 2)), el("span", { class: "m" }, fmt(metered, 2)));
      row.append(cell);
    }
    table.append(row);
  }
}

function heat(canvas, rows, color) {
  const n = rows.length;
  canvas.width = HOURS; canvas.height = Math.max(1, n);
  canvas.style.height = `${Math.min(400, Math.max(120, 4 * n))}px`;
  const ctx = canvas.getContext("2d");
  rows.forEach((r, j) => r.forEach((v, i) => { ctx.fillStyle = color(v); ctx.fillRect(i, j, 1, 1); }));
}

function drawCompact(c) {
  const dev = c.deviation_mwh.flat().filter((v) => v !== null).map(Math.abs);
  const dmax = Math.max(1e-3, ...dev);
  heat($("deviation-map"), c.deviation_mwh, (v) => diverging(v, -dmax, dmax));
  const pen = c.penalty.flat().filter((v) => v !== null);
  const pmax = Math.max(1e-3, ...pen);
  heat($("penalty-map"), c.penalty, (v) => sequential(v, pmax));
  $("deviation-map").title = `${c.agents.length} agents (rows) x 24 hours; largest |deviation| ${fmt(dmax, 2)} MWh`;
  $("penalty-map").title = `largest hourly penalty $${fmt(pmax)}`;
}

function drawBills(p) {
  const table = $("bills");
  table.replaceChildren();
  const head = el("tr");
  ["agent", "energy $", "penalty $", "credit $", "bill $", ""].forEach((t) => head.append(el("th", {}, t)));
  table.append(head);
  const rows = p.compact ? p.compact.bills : p.detail.map((a) => ({ agent: a.agent, ...a.bill }));
  for (const b of rows) {
    const row = el("tr", { "data-agent": b.agent, "data-bill": b.total, "data-settled": b.settled ? "yes" : "no" });
    row.append(el("th", {}, b.agent), el("td", {}, fmt(b.energy_charge)), el("td", {}, fmt(b.deviation_penalty)),
      el("td", {}, fmt(b.deviation_credit)), el("td", { class: "bill" }, fmt(b.total)),
      el("td", { class: b.settled ? "settled" : "accrued" }, b.settled ? "settled" : "accrued"));
    table.append(row);
  }
  $("bills-note").textContent = p.compact ? `the ${rows.length} highest and lowest of ${p.compact.agents.length}; ` +
    `all: $${fmt(p.compact.bills_total)} (mean $${fmt(p.compact.bills_mean)}), ${p.compact.settled} settled` : "";
}

function drawIncidents(p) {
  $("incident-count").textContent = p.incident_count ? `${p.incident_count} in all, the latest first` : "none yet";
  const list = $("incidents");
  list.replaceChildren();
  for (const i of p.incidents) {
    const li = el("li");
    li.append(el("span", { class: "where" }, `[${i.market_day || ""} ${i.phase}${i.hour ? " hour " + i.hour : ""}] `),
      document.createTextNode(`${i.agent || "-"}: ${i.reason}`));
    list.append(li);
  }
}

function drawFeeder(p) {
  const f = p.feeder;
  $("feeder-panel").hidden = !f;
  if (!f) return;
  $("network").textContent = `${f.network} (${f.buses.length} buses)`;
  const all = f.bus_prices.flat().filter((v) => v !== null);
  const lo = Math.min(...all), hi = Math.max(...all);
  const table = $("bus-prices");
  table.replaceChildren();
  const head = el("tr");
  head.append(el("th", {}, "bus"));
  for (let i = 1; i <= HOURS; i++) head.append(el("th", {}, i));
  table.append(head);
  const now = f.current && f.current.hour;
  f.buses.forEach((bus, b) => {
    const row = el("tr");
    row.append(el("th", {}, bus));
    f.bus_prices[b].forEach((v, i) => {
      const cell = el("td", { "data-bus": bus, "data-hour": i + 1, class: now === i + 1 ? "now" : "",
        style: `background:${diverging(v, lo, hi)}`, title: `bus ${bus} hour ${i + 1}: ${fmt(v)} $/MWh` },
        v === null ? "" : fmt(v, 0));
      if (v !== null) cell.dataset.price = v;
      row.append(cell);
    });
    table.append(row);
  });
  const c = f.current;
  $("feeder-hour").textContent = c ? c.hour : "-";
  $("feeder-stage").textContent = c ? c.stage : "-";
  bars($("voltage"), c ? c.voltage_pu : [], f.buses, { lo: 0.9, hi: 1.05, limits: [0.95, 1.05], kind: "line" });
  bars($("loading"), c ? c.line_loading : [], f.lines, { lo: 0, hi: 1.2, limits: [1.0], binding: c ? c.binding_lines : [] });
  const v = $("violations");
  v.className = c && c.violations.length ? "bad" : "";
  v.textContent = !c ? "" : c.violations.length ? `AC check, hour ${c.hour}: ${c.violations.join("; ")}` :
    `AC check, hour ${c.hour}: no violation (lowest voltage ${fmt(c.ac_v_min_pu, 3)} p.u., highest loading ` +
    `${fmt(100 * (c.ac_max_loading || 0), 0)}%)`;
}

// Values per bus (a line through them) or per line (bars), with dashed limits; over a limit in red.
function bars(svg, values, names, o) {
  svg.replaceChildren();
  const [w, h] = [360, 160], left = 34, bottom = 16, top = 4, n = values.length;
  if (!n) return;
  const hi = Math.max(o.hi, ...values), lo = Math.min(o.lo, ...values);
  const x = (i) => left + (i + 0.5) * (w - left - 4) / n;
  const y = (v) => top + (hi - v) / (hi - lo) * (h - top - bottom);
  for (const l of o.limits) svg.append(el("svg:line", { x1: left, x2: w, y1: y(l), y2: y(l), stroke: "#c0392b",
    "stroke-dasharray": "4 3" }));
  for (let k = 0; k <= 3; k++) {
    const v = lo + (hi - lo) * k / 3;
    svg.append(el("svg:text", { x: left - 3, y: y(v) + 3, "text-anchor": "end", "font-size": 9, fill: "#777" }, fmt(v, 2)));
  }
  const step = Math.max(1, Math.ceil(n / 12));
  names.forEach((name, i) => { if (i % step === 0) svg.append(el("svg:text", { x: x(i), y: h - 3,
    "text-anchor": "middle", "font-size": 9, fill: "#777" }, name)); });
  const bad = (v) => v > Math.max(...o.limits) + 1e-9 || (o.limits.length > 1 && v < o.limits[0] - 1e-9);
  if (o.kind === "line") {
    svg.append(el("svg:path", { d: values.map((v, i) => `${i ? "L" : "M"}${x(i)},${y(v)}`).join(""), fill: "none",
      stroke: "#2980b9", "stroke-width": 1.5 }));
    values.forEach((v, i) => svg.append(el("svg:circle", { cx: x(i), cy: y(v), r: 2.5,
      fill: bad(v) ? "#c0392b" : "#2980b9", "data-bus": names[i], "data-voltage": v })));
  } else {
    const bw = Math.max(1, (w - left - 4) / n * 0.7);
    values.forEach((v, i) => svg.append(el("svg:rect", { x: x(i) - bw / 2, y: y(Math.max(v, lo)), width: bw,
      height: Math.max(0, y(lo) - y(Math.max(v, lo))), fill: bad(v) ? "#c0392b" : "#7f8c8d",
      stroke: (o.binding || []).includes(i) ? "#000" : "none", "data-line": names[i], "data-loading": v })));
  }
}

function draw(p) {
  last = p;
  drawClock(p);
  drawControls(p);
  drawPrices(p);
  drawAwards(p);
  drawBills(p);
  drawIncidents(p);
  drawFeeder(p);
  document.body.dataset.messages = p.messages;
}

function control(body) {
  fetch("/control", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
}
$("play").addEventListener("click", () => last && control({ pause: !last.paused }));
$("rate").addEventListener("change", (e) => control({ rate: Number(e.target.value) }));
$("slider").addEventListener("change", (e) => control({ seek: Number(e.target.value) }));

function connect() {
  const events = new EventSource("/events");
  events.addEventListener("page", (e) => draw(JSON.parse(e.data)));
  events.onopen = () => { $("connection").textContent = "connected"; document.body.dataset.connected = "yes"; };
  events.onerror = () => {
    $("connection").textContent = "the observer has gone: the page shows what it last sent";
    document.body.dataset.connected = "no";
  };
}
connect();
