// The fleet board: aircraft x actuators, worst first or by remaining life, live.
import { get } from "/dashboard/api.js";

const STATUSES = ["ok", "learning", "watch", "unknown", "alert", "failed"]; // by severity
// The board's fleet events: the default ones, and people's changes (maintenance, config).
export const BOARD_EVENT_TYPES = ["status_changed", "fault_detected", "fault_cleared", "rul_threshold_crossed",
  "dn_threshold_crossed", "maintenance_recorded", "config_changed"];

function el(tag, cls, text) {
  const e = document.createElement(tag);
  if (cls) e.className = cls;
  if (text !== undefined) e.textContent = text;
  return e;
}

export function statusChip(status) {
  return el("span", `status status-${status}`, status);
}

export function duration(s) {
  if (s === null || s === undefined) return "";
  const a = Math.abs(s);
  if (a < 120) return `${s.toFixed(0)} s`;
  if (a < 7200) return `${(s / 60).toFixed(0)} min`;
  if (a < 172800) return `${(s / 3600).toFixed(1)} h`;
  return `${(s / 86400).toFixed(1)} d`;
}

export class Board {
  constructor(main, state) {
    this.main = main;
    this.state = state; // {sort, tail, kind}: kept across visits
    this.data = null;
    this.events = [];
    this.refreshTimer = null;
  }

  async show() {
    this.main.replaceChildren();
    const h = el("h1", "", "Fleet");
    const bar = el("div", "toolbar");
    const tail = el("input");
    tail.id = "filter-tail"; tail.placeholder = "tail contains"; tail.value = this.state.tail || "";
    const kind = el("select");
    kind.id = "filter-kind";
    const sort = el("select");
    sort.id = "sort";
    for (const [v, label] of [["status", "worst first"], ["rul", "remaining life"], ["tail", "tail"]]) {
      const o = el("option", "", label); o.value = v; sort.append(o);
    }
    sort.value = this.state.sort || "status";
    const lt = el("label", "", "Tail "); lt.append(tail);
    const lk = el("label", "", "Kind "); lk.append(kind);
    const ls = el("label", "", "Sort "); ls.append(sort);
    bar.append(lt, lk, ls);
    const legend = el("div", "legend-row");
    for (const s of STATUSES) legend.append(statusChip(s));
    this.table = el("div");
    this.table.id = "board";
    const evh = el("h2", "", "Live events");
    this.evList = el("ul", "events");
    this.evList.id = "events";
    this.main.append(h, bar, legend, this.table, evh, this.evList);
    tail.addEventListener("input", () => { this.state.tail = tail.value; this.render(); });
    kind.addEventListener("change", () => { this.state.kind = kind.value; this.render(); });
    sort.addEventListener("change", () => { this.state.sort = sort.value; this.load(); });
    this.kindSelect = kind;
    this.renderEvents();
    await this.load();
  }

  async load() {
    this.data = await get("/v1/fleet/health", { sort: this.state.sort || "status" });
    this.render();
  }

  render() {
    if (!this.data) return;
    const kinds = [...new Set(this.data.aircraft.flatMap((a) => a.actuators.map((x) => x.kind)))].sort();
    const current = this.state.kind || "";
    this.kindSelect.replaceChildren(...["", ...kinds].map((k) => { const o = el("option", "", k || "all"); o.value = k; return o; }));
    this.kindSelect.value = kinds.includes(current) ? current : "";
    const tailQ = (this.state.tail || "").trim().toLowerCase();
    const kindQ = this.kindSelect.value;
    const aircraft = this.data.aircraft
      .filter((a) => !tailQ || a.tail.toLowerCase().includes(tailQ))
      .map((a) => ({ ...a, actuators: a.actuators.filter((x) => !kindQ || x.kind === kindQ) }))
      .filter((a) => a.actuators.length);
    if (!aircraft.length) {
      this.table.replaceChildren(el("p", "meta", this.data.aircraft.length ? "No aircraft match the filters." : "No aircraft yet: register some, or run `make demo`."));
      return;
    }
    // Columns: every actuator id on the board, in the order the sort gives them.
    const columns = [];
    for (const a of aircraft) for (const x of a.actuators) if (!columns.includes(x.actuator_id)) columns.push(x.actuator_id);
    const t = el("table", "board");
    const head = el("tr");
    head.append(el("th", "", "aircraft"), ...columns.map((c) => el("th", "", c)));
    t.append(head);
    for (const a of aircraft) {
      const tr = el("tr");
      tr.dataset.tail = a.tail;
      const th = el("th");
      th.append(el("div", "", a.tail), statusChip(a.status));
      if (typeof a.open_alarms === "number" && a.open_alarms > 0) th.append(el("div", "alarms", `${a.open_alarms} open alarm${a.open_alarms > 1 ? "s" : ""}`));
      tr.append(th);
      for (const c of columns) {
        const x = a.actuators.find((y) => y.actuator_id === c);
        if (!x) { tr.append(el("td", "none")); continue; }
        const td = el("td", "cell");
        td.dataset.actuator = c;
        td.dataset.status = x.status;
        const link = el("a");
        link.href = `#/a/${encodeURIComponent(a.tail)}/${encodeURIComponent(c)}`;
        link.append(statusChip(x.status), el("div", "kind", x.kind));
        if (x.rul_q05_s !== null && x.rul_q05_s !== undefined) {
          link.append(el("div", "meta", `RUL ${duration(x.rul_q05_s)} (5 %) · ${duration(x.rul_q50_s)} (median)`));
        }
        if (x.failure) link.append(el("div", "fault", x.failure));
        for (const f of x.active_faults || []) {
          const d = el("div", "fault", `fault: ${f}`);
          d.dataset.fault = f;
          link.append(d);
        }
        if (typeof x.open_alarms === "number" && x.open_alarms > 0) link.append(el("div", "alarms", `${x.open_alarms} open alarm${x.open_alarms > 1 ? "s" : ""}`));
        if (x.t_last_s !== null) link.append(el("div", "meta", `seq ${x.last_applied_seq}/${x.last_logged_seq}`));
        td.append(link);
        tr.append(td);
      }
      t.append(tr);
    }
    this.table.replaceChildren(t);
  }

  // A fleet event: note it, patch the board at once, then read the board again within a second
  // (at most once a second, however many events arrive).
  onEvent(ev) {
    if (!ev.tail || !ev.actuator_id) return; // the stream's own messages (ready, ...)
    this.events.unshift(ev);
    this.events.length = Math.min(this.events.length, 30);
    this.renderEvents();
    if (this.data) {
      const a = this.data.aircraft.find((y) => y.tail === ev.tail);
      const x = a && a.actuators.find((y) => y.actuator_id === ev.actuator_id);
      if (x) {
        if (ev.type === "status_changed") x.status = ev.to;
        const comp = ev.detail && ev.detail.component;
        if (ev.type === "fault_detected" && comp && !x.active_faults.includes(comp)) x.active_faults.push(comp);
        if (ev.type === "fault_cleared" && comp) x.active_faults = x.active_faults.filter((f) => f !== comp);
        this.render();
      }
    }
    if (!this.refreshTimer) {
      this.refreshTimer = setTimeout(() => { this.refreshTimer = null; this.load().catch(() => {}); }, 1000);
    }
  }

  renderEvents() {
    if (!this.evList) return;
    if (!this.events.length) { this.evList.replaceChildren(el("li", "", "waiting for events (status changes, faults, RUL and Dn thresholds, maintenance, config changes)")); return; }
    this.evList.replaceChildren(...this.events.map((ev) => {
      let what = ev.type;
      if (ev.type === "status_changed") what = `status ${ev.from} -> ${ev.to}`;
      else if (ev.type === "maintenance_recorded") what = `${ev.action} by ${ev.performed_by} (baseline ${ev.baseline})`;
      else if (ev.type === "config_changed") what = `${ev.estimator} config version ${ev.version} (state ${ev.state})`;
      else if (ev.detail && ev.detail.component) what = `${ev.type} ${ev.detail.component}`;
      return el("li", "", `${ev.tail} / ${ev.actuator_id}: ${what}`);
    }));
  }
}
