// Time-series charts (uPlot) that fetch server-downsampled data and fetch finer data on zoom.
// uPlot's minified build (loaded by index.html before this module) defines window.uPlot.
const uPlot = window.uPlot;

export const COLORS = ["#1f6feb", "#e8590c", "#2f9e44", "#9c36b5", "#c92a2a", "#0c8599", "#e6a700", "#5c940d", "#862e9c", "#495057"];
export const STATUS_COLORS = {
  learning: "#4c8bf5", ok: "#2f9e44", watch: "#e6a700", alert: "#e8590c", failed: "#c92a2a", unknown: "#8a8f98",
};

// Every chart on the page, by id: tests and the screenshot script read their data from here.
export const registry = (window.fleethealth = window.fleethealth || { charts: {} }).charts;

export function resetCharts() {
  for (const k of Object.keys(registry)) delete registry[k];
}

const EPOCH_S = 1e9; // stream times from here on are epoch seconds: draw them as dates

function el(tag, cls, text) {
  const e = document.createElement(tag);
  if (cls) e.className = cls;
  if (text !== undefined) e.textContent = text;
  return e;
}

// A card with a title and a note; returns [card, body].
export function card(parent, id, title, note) {
  const c = el("section", "chart");
  c.dataset.chart = id;
  c.append(el("h3", "", title));
  if (note) c.append(el("p", "note", note));
  const body = el("div");
  c.append(body);
  parent.append(c);
  return [c, body];
}

function width(body) {
  return Math.max(320, Math.floor(body.getBoundingClientRect().width || 540));
}

// Align several {t_s, series} answers on one x axis (uPlot wants a single table).
// A spec's `scale` multiplies its values and `transform` maps them; `mirror` adds the negated
// copy as a last column, with a band between the two.
function column(values, s) {
  return values.map((v) => {
    if (v === null || v === undefined) return null;
    const x = s.transform ? s.transform(v) : v;
    return s.scale ? x * s.scale : x;
  });
}

function table(parts, specs) {
  const tables = parts.map((p, i) => [p.t_s, ...specs[i].map((s) => column(p.series[s.name] || [], s))]);
  const data = tables.length === 1 ? tables[0] : uPlot.join(tables);
  for (const [i, s] of specs.flat().entries()) if (s.mirror) data.push(data[i + 1].map((v) => (v === null ? null : -v)));
  return data;
}

function plotSpecs(specs) {
  const flat = specs.flat();
  return [...flat, ...flat.filter((s) => s.mirror).map((s) => ({ ...s, name: `-${s.name}`, label: s.label.replace("+", "-"), mirrorOf: s.name }))];
}

/**
 * A chart of one or more series fetched from `.../series`.
 * sources: [{params: {source, estimator}, series: [{name, label, color, scale, dash, band}]}]
 * lines: constant horizontal lines [{value, label, color}]
 * marks: vertical markers [{t, label, color}]
 */
export class SeriesChart {
  constructor(parent, { id, title, note, sources, fetchSeries, yLabel, lines = [], marks = [], bands = [], height = 240, range }) {
    [this.card, this.body] = card(parent, id, title, note);
    Object.assign(this, { id, sources, fetchSeries, yLabel, lines, marks, bands, height, range });
    this.specs = sources.map((s) => s.series);
    this.u = null;
    this.full = null;
    this.zoomed = false;
    this.pending = 0;
    registry[id] = this;
    this.body.addEventListener("dblclick", () => this.load());
  }

  // New data arrived: read the whole history again, unless the user has zoomed in (the zoomed
  // view is kept until a double-click goes back to the whole history).
  refresh() {
    return this.zoomed ? Promise.resolve() : this.load();
  }

  // Other series to draw (their names come from a diagnosis that a new batch may change).
  setSources(sources) {
    const names = (xs) => JSON.stringify(xs.map((s) => s.series.map((x) => [x.name, x.scale])));
    if (names(sources) === names(this.sources)) return;
    this.sources = sources;
    this.specs = sources.map((s) => s.series);
    if (this.u) { this.u.destroy(); this.u = null; }
  }

  async load(from_s, to_s) {
    if (!this.specs.flat().length) { // nothing to ask for yet (e.g. no diagnosis names the series)
      this.body.replaceChildren(el("div", "empty", "no data yet"));
      this.card.dataset.points = "0";
      return;
    }
    const points = width(this.body);
    this.zoomed = from_s !== undefined;
    const ticket = ++this.pending;
    const parts = await Promise.all(this.sources.map((s) => this.fetchSeries({ ...s.params, names: s.series.map((x) => x.name).join(","), from_s, to_s, points })));
    if (ticket !== this.pending) return; // a newer zoom has been asked for
    this.answers = parts;
    const data = table(parts, this.specs);
    this.card.dataset.samples = String(parts.reduce((n, p) => n + p.n_samples, 0));
    if (!data[0].length) {
      this.body.replaceChildren(el("div", "empty", "no data yet"));
      if (this.u) { this.u.destroy(); this.u = null; }
      return;
    }
    if (!this.u) this.create(data);
    else this.u.setData(data, from_s === undefined);
    if (from_s === undefined) this.full = [data[0][0], data[0][data[0].length - 1]];
    this.card.dataset.points = String(this.countPoints());
  }

  countPoints() {
    if (!this.u) return 0;
    return this.u.data.slice(1).reduce((n, ys) => n + ys.filter((v) => v !== null && v !== undefined && Number.isFinite(v)).length, 0);
  }

  create(data) {
    const flat = plotSpecs(this.specs);
    const series = [{ label: "time" }, ...flat.map((s, i) => ({
      label: s.label || s.name,
      stroke: s.color || COLORS[i % COLORS.length],
      width: s.width || 1.25,
      dash: s.dash,
      fill: s.fill,
      spanGaps: true,
      points: { show: s.points || false, size: 4 },
      paths: s.step ? uPlot.paths.stepped({ align: 1 }) : undefined,
    }))];
    const pairs = [...this.bands, ...flat.filter((s) => s.mirrorOf).map((s) => [s.mirrorOf, s.name, "rgba(232,89,12,0.10)"])];
    const bands = pairs.map((b) => ({ series: [flat.findIndex((s) => s.name === b[0]) + 1, flat.findIndex((s) => s.name === b[1]) + 1], fill: b[2] || "rgba(31,111,235,0.12)" }));
    const epoch = data[0][0] >= EPOCH_S;
    const self = this;
    const opts = {
      width: width(this.body),
      height: this.height,
      series,
      bands,
      scales: { x: { time: epoch }, y: this.range ? { range: this.range } : {} },
      axes: [{}, { label: this.yLabel, size: 60 }],
      cursor: { drag: { x: true, y: false } },
      legend: { live: true },
      hooks: {
        draw: [(u) => self.drawOverlays(u)],
        setSelect: [(u) => {
          if (u.select.width < 3) return;
          const from = u.posToVal(u.select.left, "x"), to = u.posToVal(u.select.left + u.select.width, "x");
          self.load(from, to);
        }],
      },
    };
    this.body.replaceChildren(); // the "no data yet" of an earlier load
    this.u = new uPlot(opts, data, this.body);
  }

  drawOverlays(u) {
    const ctx = u.ctx;
    ctx.save();
    ctx.lineWidth = 1;
    const { left, top, width: w, height: h } = u.bbox;
    for (const ln of this.lines) {
      if (ln.value === null || ln.value === undefined) continue;
      const y = u.valToPos(ln.value, "y", true);
      if (y < top || y > top + h) continue;
      ctx.strokeStyle = ln.color || "#c92a2a";
      ctx.setLineDash([6, 4]);
      ctx.beginPath(); ctx.moveTo(left, y); ctx.lineTo(left + w, y); ctx.stroke();
      ctx.setLineDash([]);
      ctx.fillStyle = ln.color || "#c92a2a";
      ctx.font = `${11 * devicePixelRatio}px system-ui`;
      ctx.fillText(ln.label, left + 4, y - 3);
    }
    for (const [i, m] of this.marks.entries()) {
      const x = u.valToPos(m.t, "x", true);
      if (x < left || x > left + w) continue;
      ctx.strokeStyle = m.color || "#c92a2a";
      ctx.beginPath(); ctx.moveTo(x, top); ctx.lineTo(x, top + h); ctx.stroke();
      ctx.fillStyle = m.color || "#c92a2a";
      ctx.font = `${11 * devicePixelRatio}px system-ui`;
      ctx.fillText(m.label, x + 3, top + (12 + 13 * (i % 3)) * devicePixelRatio); // staggered: marks crowd
    }
    ctx.restore();
  }
}

/** A chart of points given directly (no fetching): [{x:[], y:{name:[]}}]. */
export function staticChart(parent, { id, title, note, x, series, xLabel, yLabel, height = 220, time = false, bars = false, bands = [] }) {
  const [c, body] = card(parent, id, title, note);
  const data = [x, ...series.map((s) => s.values)];
  const self = { id, card: c };
  registry[id] = self;
  if (!x.length) {
    body.replaceChildren(el("div", "empty", "no data yet"));
    c.dataset.points = "0";
    return self;
  }
  const opts = {
    width: width(body), height,
    series: [{ label: xLabel || "x" }, ...series.map((s, i) => ({
      label: s.label, stroke: s.color || COLORS[i % COLORS.length], width: 1.5, fill: s.fill,
      points: { show: s.points ?? !bars, size: 6 }, paths: bars ? uPlot.paths.bars({ size: [0.6, 40] }) : undefined,
    }))],
    bands: bands.map(([a, b]) => ({ series: [a, b], fill: "rgba(232,89,12,0.12)" })),
    scales: { x: { time } },
    axes: [{ label: xLabel }, { label: yLabel, size: 60 }],
  };
  self.u = new uPlot(opts, data, body);
  c.dataset.points = String(series.reduce((n, s) => n + s.values.filter((v) => v !== null && Number.isFinite(v)).length, 0));
  return self;
}
