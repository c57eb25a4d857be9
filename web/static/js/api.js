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

export async function postForm(url, formData) {
  return parse(await fetch(url, { method: "POST", credentials: "same-origin", body: formData }));
}

/** Replace the children of `element` with a server-rendered partial fetched from `url`. */
export async function refreshPartial(element, url) {
  const response = await fetch(url, { credentials: "same-origin", headers: { Accept: "text/html" } });
  if (!response.ok) throw new ApiError(response.status, await response.text());
  const template = document.createElement("template");
  template.innerHTML = await response.text();
  element.replaceChildren(template.content);
}

/** Show a message in an <output>; kind is "ok" or "error". */
export function say(output, text, kind) {
  output.textContent = text;
  output.dataset.kind = kind;
}
