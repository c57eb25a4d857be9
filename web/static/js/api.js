// Small helpers for the REST API (same origin; the session cookie authenticates writes).

/** Error thrown for a non-2xx answer; `message` is the API's detail (names the field). */
export class ApiError extends Error {
  constructor(status, detail, field) {
    // the field is said once: not again when the detail already names it (or its last part)
    const last = field ? String(field).split(": ").pop() : "";
    super(field && !String(detail).includes(last) ? `${field}: ${detail}` : String(detail));
    this.status = status;
    this.field = field;
  }
}

async function parse(response) {
  const type = response.headers.get("content-type") || "";
  const body = type.includes("application/json") ? await response.json() : await response.text();
  if (!response.ok) {
    const detail = typeof body === "object" && body !== null ? body.detail ?? JSON.stringify(body) : body;
    const field = typeof body === "object" && body !== null ? body.field : undefined;
    throw new ApiError(response.status, typeof detail === "string" ? detail : JSON.stringify(detail), field);
  }
  return body;
}

export async function getJSON(url) {
  return parse(await fetch(url, { credentials: "same-origin", headers: { Accept: "application/json" } }));
}

export async function postJSON(url, data) {
  return parse(await fetch(url, {
    method: "POST",
    credentials: "same-origin",
    headers: { "Content-Type": "application/json", Accept: "application/json" },
    body: JSON.stringify(data),
  }));
}

export async function putJSON(url, data) {
  return parse(await fetch(url, {
    method: "PUT",
    credentials: "same-origin",
    headers: { "Content-Type": "application/json", Accept: "application/json" },
    body: JSON.stringify(data),
  }));
}

export async function postForm(url, formData) {
  return parse(await fetch(url, { method: "POST", credentials: "same-origin", body: formData }));
}

const shownPartials = new WeakMap(); // element -> the partial's HTML it shows

/** Replace the children of `element` with a server-rendered partial fetched from `url`, unless the
 * partial is the one it shows already (a poll that changed nothing leaves the nodes alone: a link
 * under the pointer is not swapped from under a click, a hover does not flicker). */
export async function refreshPartial(element, url) {
  const response = await fetch(url, { credentials: "same-origin", headers: { Accept: "text/html" } });
  if (!response.ok) throw new ApiError(response.status, await response.text());
  const html = await response.text();
  if (shownPartials.get(element) === html) return;
  const template = document.createElement("template");
  template.innerHTML = html;
  element.replaceChildren(template.content);
  shownPartials.set(element, html);
}

/** Show a message in an <output>; kind is "ok" or "error". */
export function say(output, text, kind) {
  output.textContent = text;
  output.dataset.kind = kind;
}
