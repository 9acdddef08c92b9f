// JSON API client of the workbench page (same origin; the access token travels as a cookie set by the page URL).

export class ApiError extends Error {
  constructor(status, reason) {
    super(reason);
    this.status = status;
  }
}

async function check(resp) {
  if (resp.ok) return resp;
  let reason = resp.statusText;
  try {
    reason = (await resp.json()).error || reason;
  } catch (_) {
    /* not JSON */
  }
  throw new ApiError(resp.status, reason);
}

export async function get(path) {
  return (await check(await fetch(path, { credentials: "same-origin" }))).json();
}

export async function getBytes(path) {
  return (await check(await fetch(path, { credentials: "same-origin" }))).arrayBuffer();
}

export async function send(method, path, body) {
  const resp = await fetch(path, {
    method,
    credentials: "same-origin",
    headers: { "Content-Type": "application/json" },
    body: body === undefined ? undefined : JSON.stringify(body),
  });
  return (await check(resp)).json();
}

export async function postForImage(path, body) {
  const resp = await check(
    await fetch(path, {
      method: "POST",
      credentials: "same-origin",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify(body),
    }),
  );
  const meta = JSON.parse(resp.headers.get("X-Peek") || "{}");
  return { url: URL.createObjectURL(await resp.blob()), meta };
}

export function events(onEvent, onState) {
  const src = new EventSource("/api/events");
  src.onopen = () => onState(true);
  src.onerror = () => onState(false);
  src.onmessage = (e) => onEvent(JSON.parse(e.data));
  return src;
}

export const photoUrl = (id) => `/api/photos/${id}/image`;
export const thumbUrl = (id) => `/api/photos/${id}/thumb`;
export const overlayUrl = (id, mode) => `/api/photos/${id}/overlay/${mode}`;
export const maskUrl = (id, kind) => `/api/photos/${id}/mask/${kind}`;
