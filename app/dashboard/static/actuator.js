// One actuator: its status and one set of plots per kind.
import { actuatorPath, get } from "/dashboard/api.js";
import { registry, resetCharts, SeriesChart, STATUS_COLORS, staticChart } from "/dashboard/charts.js";
import { duration, statusChip } from "/dashboard/board.js";

const DEG = 180 / Math.PI;

function el(tag, cls, text) {
  const e = document.createElement(tag);
  if (cls) e.className = cls;
  if (text !== undefined) e.textContent = text;
  return e;
}

function fact(label, value) {
  const d = el("div");
  d.append(el("b", "", label), typeof value === "string" ? document.createTextNode(value) : value);
  return d;
}

function smallTable(headers, rows) {
  const t = el("table", "small");
  const h = el("tr");
  h.append(...headers.map((x) => el("th", "", x)));
  t.append(h);
  for (const r of rows) {
    const tr = el("tr");
    tr.append(...r.map((x) => el("td", "", x === null || x === undefined ? "" : String(x))));
    t.append(tr);
  }
  return t;
}

const fmt = (v, d = 4) => (v === null || v === undefined ? "" : Number(v).toPrecision(d));

const lastSample = (t) => (t === null || t === undefined ? "none" : (t >= 1e9 ? new Date(t * 1000).toISOString() : `${t} s`));

// Fleet events that change what an actuator page shows (besides `applied`, one per batch).
export const PAGE_EVENT_TYPES = ["applied", "status_changed", "fault_detected", "fault_cleared", "rul_threshold_crossed",
  "dn_threshold_crossed", "maintenance_recorded", "config_changed"];
const REFRESH_MS = 1000; // the page reads its data again at most once a second

// An actuator's page, kept live by the fleet events of its tail (see app.js): an `applied` batch
// updates the facts at once, and every event of this actuator reads its data again (the plots
// at their whole history, unless zoomed in; the tables) within a second.
export class ActuatorPage {
  constructor(main, tail, actuatorId) {
    Object.assign(this, { main, tail, actuatorId, base: actuatorPath(tail, actuatorId) });
    this.timer = null;
    this.running = null;
    this.again = false;
  }

  async show() {
    const { base, tail, actuatorId } = this;
    const [act, health] = await Promise.all([get(base), get(`${base}/health`)]);
    this.main.replaceChildren();
    resetCharts();
    this.facts = el("div", "facts");
    this.facts.id = "facts";
    this.reasons = el("div");
    this.reasons.id = "reasons";
    const note = el("p", "meta", "Drag across a plot to zoom in (finer data is fetched), double-click to zoom out. The page follows new telemetry live.");
    const grid = el("div", "charts");
    grid.id = "charts";
    this.main.append(el("h1", "", `${tail} / ${actuatorId}`), this.facts, this.reasons, note, grid);
    this.renderHealth(act, health);
    this.act = act;
    const fetchSeries = (params) => get(`${base}/series`, params);
    const plots = { ema_voltage: fakfPlots, friction_drive: deteriorationPlots, flight_controls: stmmaePlots, sha_ema: darrPlots }[act.kind];
    if (!plots) { grid.append(el("p", "meta", `No plots for kind ${act.kind}.`)); return; }
    this.plots = plots({ base, act, grid, fetchSeries });
    await this.plots.refresh();
  }

  renderHealth(act, health) {
    this.facts.dataset.status = health.status;
    this.facts.dataset.appliedSeq = String(health.last_applied_seq);
    this.facts.replaceChildren(fact("status", statusChip(health.status)), fact("kind", act.kind),
      fact("applied / logged", `${health.last_applied_seq} / ${health.last_logged_seq}`),
      fact("last sample", lastSample(health.t_last_s)));
    if (health.failure) this.facts.append(fact("failure", health.failure));
    this.reasons.replaceChildren(...Object.entries(health.estimators).map(([name, est]) => {
      const p = el("p", "reasons");
      p.append(el("b", "", `${name}: `), statusChip(est.status), document.createTextNode(" " + (est.reasons.join("; ") || "no reasons given")));
      return p;
    }));
  }

  onEvent(ev) {
    if (ev.tail !== this.tail || ev.actuator_id !== this.actuatorId || !this.facts) return;
    if (ev.type === "applied" && ev.seq > Number(this.facts.dataset.appliedSeq)) {
      // At once, before the data is read again: the status and position of the batch applied.
      this.facts.dataset.status = ev.status;
      this.facts.dataset.appliedSeq = String(ev.seq);
      this.facts.firstChild.replaceWith(fact("status", statusChip(ev.status)));
    }
    if (!this.timer) this.timer = setTimeout(() => { this.timer = null; this.refresh(); }, REFRESH_MS);
  }

  // Read health and every plot again; a refresh asked for while one runs follows it.
  async refresh() {
    if (this.running) { this.again = true; return; }
    this.running = (async () => {
      try {
        const [act, health] = await Promise.all([get(this.base), get(`${this.base}/health`)]);
        this.act = act;
        this.renderHealth(act, health);
        if (this.plots) await this.plots.refresh(act);
      } catch { /* the next event tries again */ }
    })();
    await this.running;
    this.running = null;
    if (this.again) { this.again = false; this.onEvent({ tail: this.tail, actuator_id: this.actuatorId }); }
  }

  stop() {
    if (this.timer) clearTimeout(this.timer);
    this.timer = null;
    this.facts = null;
  }
}

// A section rebuilt on each refresh (tables, charts of points given directly).
function section(grid) {
  const box = el("div", "section");
  box.style.display = "contents";
  grid.append(box);
  return {
    box,
    replace(...children) {
      for (const c of box.querySelectorAll("[data-chart]")) { const r = registry[c.dataset.chart]; if (r && r.u && r.u.destroy) r.u.destroy(); }
      box.replaceChildren(...children);
    },
  };
}

// ---------------------------------------------------------------- FAKF (ema_voltage)
function fakfPlots({ grid, fetchSeries, base }) {
  const est = { source: "outputs", estimator: "fakf" };
  const charts = [
    new SeriesChart(grid, {
      id: "fakf-voltage", title: "Motor voltage: measured and estimated", yLabel: "V", fetchSeries,
      note: "measured: the logged telemetry; estimated: the filter's posterior; model: the identified model driven by current alone",
      sources: [
        { params: est, series: [{ name: "voltage_estimate", label: "estimated", color: "#1f6feb" }, { name: "voltage_model", label: "model", color: "#e8590c", dash: [5, 3] }] },
        { params: { source: "telemetry" }, series: [{ name: "voltage", label: "measured", color: "rgba(60,60,60,0.55)" }] },
      ],
    }),
    new SeriesChart(grid, {
      id: "fakf-innovation", title: "Innovation with its ±2σ band", yLabel: "V", fetchSeries,
      note: "innovation = measured - prior; band ±2·sqrt(S) from the filter's innovation variance",
      sources: [{ params: est, series: [{ name: "innovation", label: "innovation", color: "#1f6feb" }, { name: "innovation_var", label: "+2σ", color: "rgba(232,89,12,0.7)", transform: (v) => 2 * Math.sqrt(v), mirror: true }] }],
    }),
    new SeriesChart(grid, {
      id: "fakf-health", title: "Health indicators per window", fetchSeries,
      note: "innovation RMS ratio (1 = as expected), share of NIS in bounds, coefficient drift, prior/persistence RMS ratio",
      sources: [{ params: { source: "health", estimator: "fakf" }, series: [
        { name: "innovation_rms_ratio", label: "innovation RMS ratio", points: true },
        { name: "nis_in_bounds", label: "NIS in bounds", points: true },
        { name: "coef_drift", label: "coefficient drift", points: true },
        { name: "prior_to_persistence_rms_ratio", label: "prior/persistence RMS", points: true },
      ] }],
      lines: [{ value: 1, label: "1", color: "#8a8f98" }],
    }),
  ];
  const extra = section(grid);
  return {
    async refresh() {
      await Promise.all(charts.map((c) => c.refresh()));
      const events = (await get(`${base}/events`, { limit: 100 })).items;
      const rows = events.map((e) => [e.kind, new Date(e.t_s * 1000).toISOString(), JSON.stringify(e.detail).slice(0, 200)]);
      const box = el("section", "chart");
      box.dataset.chart = "fakf-events";
      box.append(el("h3", "", "Estimator events"), rows.length ? smallTable(["event", "time", "detail"], rows.slice(-10)) : el("p", "note", "none yet"));
      extra.replace(box);
    },
  };
}

// ---------------------------------------------------------------- deterioration EKF (friction_drive)
function deteriorationPlots({ grid, fetchSeries, base, act }) {
  const cfg = act.estimators.deterioration_ekf || {};
  const est = { source: "outputs", estimator: "deterioration_ekf" };
  const dn = new SeriesChart(grid, {
    id: "dekf-dn", title: "Normalized deterioration Dn with its 3σ band", yLabel: "Dn", fetchSeries,
    sources: [{ params: est, series: [
      { name: "dn", label: "Dn", color: "#1f6feb" },
      { name: "dn_lower", label: "lower (3σ)", color: "rgba(31,111,235,0.35)" },
      { name: "dn_upper", label: "upper (3σ)", color: "rgba(31,111,235,0.35)" },
    ] }],
    bands: [["dn_upper", "dn_lower"]],
    lines: [
      { value: cfg.dn_watch, label: `watch ${cfg.dn_watch}`, color: STATUS_COLORS.watch },
      { value: cfg.dn_alert, label: `alert ${cfg.dn_alert}`, color: STATUS_COLORS.alert },
      { value: cfg.rul_failure_dn, label: `failure ${cfg.rul_failure_dn}`, color: STATUS_COLORS.failed },
    ],
  });
  const wear = new SeriesChart(grid, {
    id: "dekf-alpha", title: "Contact quality α and wear rate m", fetchSeries,
    sources: [{ params: est, series: [{ name: "alpha", label: "α" }, { name: "m", label: "m (wear rate) x 1000", scale: 1000 }] }],
  });
  const extra = section(grid);
  return {
    async refresh() {
      await Promise.all([dn.refresh(), wear.refresh()]);
      await rulCharts(extra, base);
    },
  };
}

async function rulCharts(extra, base) {
  const rul = await get(`${base}/rul`, { estimator: "deterioration_ekf", limit: 5000 });
  extra.replace();
  const grid = extra.box;
  const items = rul.items;
  staticChart(grid, {
    id: "dekf-rul", title: "Remaining useful life: median and 5-95 % band", time: items.length && items[0].t_s >= 1e9,
    note: "Monte Carlo prognoses, seconds of stream time until Dn reaches the failure threshold",
    x: items.map((r) => r.t_s), yLabel: "RUL, s",
    series: [
      { label: "q05", values: items.map((r) => r.q05_s), color: "rgba(232,89,12,0.6)" },
      { label: "median", values: items.map((r) => r.q50_s), color: "#e8590c" },
      { label: "q95", values: items.map((r) => r.q95_s), color: "rgba(232,89,12,0.6)" },
    ],
    bands: [[3, 1]],
  });
  const last = rul.latest.deterioration_ekf;
  if (last && last.mean_s !== null && last.std_s) {
    const { mean_s: m, std_s: sd } = last;
    const lo = Math.max(0, Math.min(last.q05_s ?? m, m - 4 * sd)), hi = Math.max(last.q95_s ?? m, m + 4 * sd);
    const xs = Array.from({ length: 121 }, (_, i) => lo + ((hi - lo) * i) / 120);
    const pdf = (x) => Math.exp(-0.5 * ((x - m) / sd) ** 2) / (sd * Math.sqrt(2 * Math.PI));
    const q = [last.q05_s, last.q50_s, last.q95_s];
    staticChart(grid, {
      id: "dekf-rul-dist", title: `Latest RUL distribution (${duration(last.q50_s)} median)`, xLabel: "RUL, s", yLabel: "density",
      note: "curve: normal density with the prognosis' mean and std; points: its Monte Carlo 5 %, 50 % and 95 % quantiles",
      x: xs, series: [
        { label: "normal(mean, std)", values: xs.map(pdf), color: "#1f6feb", points: false },
        { label: "quantiles", values: xs.map((x, i) => (q.some((v) => v !== null && Math.abs(v - x) <= (hi - lo) / 240 + 1e-12) || q.some((v) => v !== null && i > 0 && xs[i - 1] < v && v <= x) ? pdf(x) : null)), color: "#e8590c" },
      ],
    });
  } else {
    const box = el("section", "chart");
    box.dataset.chart = "dekf-rul-dist";
    box.append(el("h3", "", "Latest RUL distribution"), el("p", "note", last ? "Failure threshold not reached within the prediction horizon." : "No prognosis yet."));
    grid.append(box);
  }
}

// ---------------------------------------------------------------- STMMAE (flight_controls)
function stmmaePlots({ grid, fetchSeries, base }) {
  const est = { source: "outputs", estimator: "stmmae" };
  const prob = new SeriesChart(grid, {
    id: "stmmae-prob", title: "Hypothesis probabilities", fetchSeries, range: [0, 1], sources: [],
    note: "nominal and single-surface hypotheses (pairs omitted); vertical lines: fault detections and clearances",
  });
  const deflection = new SeriesChart(grid, {
    id: "stmmae-deflection", title: "Estimated surface deflections", yLabel: "deg", fetchSeries, sources: [],
  });
  const extra = section(grid);
  return {
    async refresh() {
      // The series and marks come from the diagnosis, which each batch may change.
      const faults = await get(`${base}/faults`, { limit: 200 });
      const diag = (faults.estimators.stmmae || {}).diagnosis || {};
      const hyps = Object.keys(diag.probabilities || {}).filter((h) => !h.includes("+"));
      const surfaces = Object.keys(diag.deflection_estimates_deg || {});
      const marks = faults.events.map((e) => ({ t: e.t_s, label: `${e.kind === "fault_detected" ? "detected" : "cleared"} ${e.detail.component || ""}`, color: e.kind === "fault_detected" ? STATUS_COLORS.failed : STATUS_COLORS.ok }));
      prob.setSources([{ params: est, series: (hyps.length ? hyps : ["nominal"]).map((h) => ({ name: `prob_${h}`, label: h })) }]);
      deflection.setSources([{ params: est, series: surfaces.map((s) => ({ name: `deflection_${s}`, label: s, scale: DEG })) }]);
      prob.marks = deflection.marks = marks;
      await Promise.all([prob.refresh(), deflection.refresh()]);
      extra.replace(stmmaeTables(faults, diag));
    },
  };
}

function stmmaeTables(faults, diag) {
  const box = el("section", "chart");
  box.append(el("h3", "", "Current diagnosis"));
  const probs = Object.entries(diag.surface_fault_probabilities || {}).map(([s, p]) => [s, fmt(p, 3), fmt((diag.deflection_estimates_deg || {})[s], 3)]);
  box.append(probs.length ? smallTable(["surface", "fault probability", "deflection, deg"], probs) : el("p", "note", "no diagnosis yet"));
  const active = faults.active_faults.map((f) => [f.detail.component, f.detail.fault_kind, new Date(f.t_s * 1000).toISOString()]);
  box.append(el("h3", "", "Active faults"), active.length ? smallTable(["surface", "kind", "detected"], active) : el("p", "note", "none"));
  return box;
}

// ---------------------------------------------------------------- DARR + FEKF (sha_ema)
function darrPlots({ grid, fetchSeries, base }) {
  const est = { source: "outputs", estimator: "darr_fekf" };
  const residualChart = new SeriesChart(grid, {
    id: "darr-residuals", title: "Residuals against their thresholds", yLabel: "residual / threshold", fetchSeries, sources: [],
    note: "each residual divided by its current threshold: beyond ±1 the residual is exceeded",
    lines: [{ value: 1, label: "+threshold", color: STATUS_COLORS.alert }, { value: -1, label: "-threshold", color: STATUS_COLORS.alert }],
  });
  const parameterChart = new SeriesChart(grid, {
    id: "darr-parameters", title: "FEKF parameter estimates, relative to nominal", yLabel: "estimate / nominal", fetchSeries, sources: [],
    note: "fused estimates of the implicated subsystems' parameters (empty until a fault is isolated)",
    lines: [{ value: 1, label: "nominal", color: "#8a8f98" }],
  });
  const extra = section(grid);
  return {
    async refresh() {
      // The residuals, thresholds and parameters come from the diagnosis, which each batch may change.
      const faults = await get(`${base}/faults`, { limit: 200 });
      const diag = (faults.estimators.darr_fekf || {}).diagnosis || {};
      const residuals = diag.residuals || {};
      const params = diag.parameters || {};
      residualChart.setSources([{ params: est, series: Object.keys(residuals).map((r) => ({ name: r, label: r, scale: residuals[r].threshold ? 1 / residuals[r].threshold : 1 })) }]);
      parameterChart.setSources([{ params: est, series: Object.keys(params).map((p) => ({ name: p, label: p, scale: params[p].nominal ? 1 / params[p].nominal : 1 })) }]);
      residualChart.marks = parameterChart.marks = faults.events.filter((e) => e.kind === "fault_detected").map((e) => ({ t: e.t_s, label: `detected ${e.detail.component || ""}`, color: STATUS_COLORS.failed }));
      await Promise.all([residualChart.refresh(), parameterChart.refresh()]);
      extra.replace(darrTables(diag));
    },
  };
}

function darrTables(diag) {
  const residuals = diag.residuals || {};
  const names = Object.keys(residuals);
  const params = diag.parameters || {};
  const box = el("section", "chart");
  box.append(el("h3", "", "Coherence vector"));
  box.append(diag.coherence_vector ? smallTable(names.length ? names : diag.coherence_vector.map((_, i) => `r${i + 1}`), [diag.coherence_vector]) : el("p", "note", "no diagnosis yet"));
  const cands = (diag.candidates || []).slice(0, 12).map((c, i) => [i + 1, `{${c.join(", ")}}`]);
  box.append(el("h3", "", `Candidate fault sets (${(diag.candidates || []).length})`), cands.length ? smallTable(["#", "set"], cands) : el("p", "note", "none"));
  const prow = Object.entries(params).map(([p, v]) => [p, fmt(v.estimate), `${fmt(v.lower)} .. ${fmt(v.upper)}`, fmt(v.nominal), v.relative_change === null || v.relative_change === undefined ? "" : `${(100 * v.relative_change).toFixed(1)} %`]);
  box.append(el("h3", "", "Parameter estimates"), prow.length ? smallTable(["parameter", "estimate", "bounds", "nominal", "change"], prow) : el("p", "note", "none"));
  return box;
}
