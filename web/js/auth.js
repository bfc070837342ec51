// Sign-in for a team server (docs/team.md): a server started with `--tokens` answers 401 on
// every /api/ route without `Authorization: Bearer TOKEN` (a WebSocket, which cannot set
// headers, may send the `access_token` query parameter instead).
//
// The viewer takes the token from the page URL (`?access_token=T`, `#token=T` or
// `#access_token=T`) or from its sign-in form, and keeps it for this tab only
// (sessionStorage: gone when the tab closes, not seen by other tabs). A token in the URL is
// removed from the address bar at once, so the link the viewer shares and the history never
// carry it. Nothing here logs the token or puts it in an error message.

const KEY = "translux.token";
// When the browser refuses sessionStorage (storage disabled), the token lives as long as
// the page.
let held = null;

/** This tab's token, or null. */
export function token() {
  try {
    return sessionStorage.getItem(KEY) ?? held;
  } catch {
    return held;
  }
}

export function setToken(t) {
  held = t;
  try {
    sessionStorage.setItem(KEY, t);
  } catch {
    // kept in `held` for this page
  }
}

export function clearToken() {
  held = null;
  try {
    sessionStorage.removeItem(KEY);
  } catch {
    // nothing stored
  }
}

/**
 * Moves a token in the page URL into the session and out of the address bar (with
 * `history.replaceState`, which fires no `hashchange`). Returns whether the URL had one.
 */
export function takeTokenFromUrl() {
  const url = new URL(location.href);
  const fromQuery = url.searchParams.get("access_token");
  const hash = new URLSearchParams(url.hash.replace(/^#/, ""));
  const fromHash = hash.get("token") ?? hash.get("access_token");
  if (fromQuery === null && fromHash === null) return false;
  url.searchParams.delete("access_token");
  let rest = url.hash;
  if (fromHash !== null) {
    hash.delete("token");
    hash.delete("access_token");
    rest = hash.toString() ? "#" + hash.toString() : "";
  }
  history.replaceState(null, "", url.pathname + url.search + rest);
  const t = (fromHash ?? fromQuery).trim();
  if (t) setToken(t);
  return true;
}

/** `fetch` with this tab's token as `Authorization: Bearer`. */
export function apiFetch(url, init = {}) {
  const headers = new Headers(init.headers || {});
  const t = token();
  if (t) headers.set("Authorization", `Bearer ${t}`);
  return fetch(url, { ...init, headers });
}

/** A WebSocket URL carrying this tab's token as `access_token`. */
export function withAccessToken(url) {
  const t = token();
  if (!t) return url;
  return `${url}${url.includes("?") ? "&" : "?"}access_token=${encodeURIComponent(t)}`;
}

/** Whether an HTTP status is the server turning the token (or its absence) down. */
export const isDenial = (status) => status === 401 || status === 403;

/** What a 401 or 403 means for the person at the screen; `message` is the server's. */
export function denialMessage(status, message) {
  if (status === 403) {
    return `The server refuses this token (403: ${message}). Sign in with a token that may view scenes.`;
  }
  if (token()) {
    return `The server does not accept this token (401: ${message}). Enter a valid token.`;
  }
  return `This server wants an access token (401: ${message}). Enter yours below, or open ` +
    "the page with ?access_token=TOKEN.";
}
