// The dashboard: a key for this browser session, then the fleet board or an actuator page.
import { ApiError, fleetEvents, get, key } from "/dashboard/api.js";
import { Board, BOARD_EVENT_TYPES } from "/dashboard/board.js";
import { ActuatorPage, PAGE_EVENT_TYPES } from "/dashboard/actuator.js";

const main = document.getElementById("main");
const login = document.getElementById("login");
const loginError = document.getElementById("login-error");
const live = document.getElementById("live");
const forget = document.getElementById("forget");
const crumbs = document.getElementById("crumbs");
const boardState = { sort: "status", tail: "", kind: "" };
let view = null; // the board or an actuator page: what the fleet events go to
let stopEvents = null;
let subscribed = null; // the subscription's query, one per kind of view

// The fleet event stream of the view: the board hears the whole fleet's events, an actuator
// page those of its tail, every applied batch included (it filters its own actuator's).
function subscribe(query) {
  if (stopEvents && subscribed === query) return;
  if (stopEvents) stopEvents();
  subscribed = query;
  stopEvents = fleetEvents(query, (ev) => { if (view) view.onEvent(ev); }, (on) => {
    live.textContent = on ? "live" : "offline";
    live.classList.toggle("on", on);
  });
}

function askForKey(message) {
  if (stopEvents) { stopEvents(); stopEvents = null; }
  if (view && view.stop) view.stop();
  view = null;
  key.clear();
  main.replaceChildren();
  crumbs.replaceChildren();
  forget.hidden = true;
  login.hidden = false;
  loginError.textContent = message || "";
  document.getElementById("key").focus();
}

function refused(err) {
  if (err instanceof ApiError && err.status === 401) return "The key was refused (unknown or revoked).";
  if (err instanceof ApiError && err.status === 403) return "This key lacks the read scope.";
  return null;
}

async function route() {
  if (!key.get()) return askForKey();
  login.hidden = true;
  forget.hidden = false;
  const m = location.hash.match(/^#\/a\/([^/]+)\/([^/]+)$/);
  if (view && view.stop) view.stop();
  view = null;
  try {
    if (m) {
      const tail = decodeURIComponent(m[1]), act = decodeURIComponent(m[2]);
      const a = document.createElement("a");
      a.href = "#/"; a.textContent = "fleet";
      crumbs.replaceChildren(a, document.createTextNode(` / ${tail} / ${act}`));
      // Subscribed before the first read, so that no batch applied meanwhile goes unseen.
      subscribe(new URLSearchParams({ tail, types: PAGE_EVENT_TYPES.join(",") }).toString());
      const page = new ActuatorPage(main, tail, act);
      view = page;
      await page.show();
    } else {
      crumbs.replaceChildren();
      subscribe(new URLSearchParams({ types: BOARD_EVENT_TYPES.join(",") }).toString());
      const board = new Board(main, boardState);
      view = board;
      await board.show();
    }
    document.body.dataset.ready = "true";
  } catch (err) {
    const why = refused(err);
    if (why) return askForKey(why);
    const p = document.createElement("p");
    p.className = "error";
    p.textContent = `Could not load: ${err.message}`;
    main.replaceChildren(p);
  }
}

login.addEventListener("submit", async (e) => {
  e.preventDefault();
  const candidate = document.getElementById("key").value.trim();
  try {
    await get("/v1/fleet/health", {}, candidate);
  } catch (err) {
    loginError.textContent = refused(err) || `Could not reach the server: ${err.message}`;
    return;
  }
  key.set(candidate);
  document.getElementById("key").value = "";
  route();
});
forget.addEventListener("click", () => askForKey("Key forgotten."));
window.addEventListener("hashchange", () => { delete document.body.dataset.ready; route(); });
route();
