// Calls to the read API with the key of this browser session.
const KEY = "fleethealth.key";

export class ApiError extends Error {
  constructor(status, error, detail) {
    super(`${status} ${error}: ${detail}`);
    this.status = status;
    this.error = error;
    this.detail = detail;
  }
}

export const key = {
  get: () => sessionStorage.getItem(KEY),
  set: (k) => sessionStorage.setItem(KEY, k),
  clear: () => sessionStorage.removeItem(KEY),
};

export async function get(path, params = {}, apiKey = key.get()) {
  const q = new URLSearchParams();
  for (const [k, v] of Object.entries(params)) if (v !== undefined && v !== null) q.set(k, String(v));
  const url = q.toString() ? `${path}?${q}` : path;
  const r = await fetch(url, { headers: { Authorization: `Bearer ${apiKey}` } });
  if (!r.ok) {
    let body = {};
    try { body = await r.json(); } catch { /* not JSON */ }
    throw new ApiError(r.status, body.error || r.statusText, body.detail || "");
  }
  return r.json();
}

export const enc = encodeURIComponent;
export const actuatorPath = (tail, act) => `/v1/aircraft/${enc(tail)}/actuators/${enc(act)}`;

// The fleet event stream (`query`: its tail and types): authenticates with its first message
// (browsers cannot set headers on a WebSocket), reconnects with back-off, and hands every event
// to onEvent.
export function fleetEvents(query, onEvent, onState) {
  let ws = null, closed = false, delay = 1000;
  const open = () => {
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    ws = new WebSocket(`${proto}//${location.host}/v1/fleet/events${query ? `?${query}` : ""}`);
    ws.onopen = () => { ws.send(JSON.stringify({ type: "auth", key: key.get() })); onState(true); delay = 1000; };
    ws.onmessage = (m) => {
      let ev;
      try { ev = JSON.parse(m.data); } catch { return; }
      if (ev.type === "error") return;
      onEvent(ev);
    };
    ws.onclose = () => {
      if (closed) return; // replaced by another subscription
      onState(false);
      setTimeout(open, delay);
      delay = Math.min(delay * 2, 15000);
    };
  };
  open();
  return () => { closed = true; if (ws) ws.close(); };
}
