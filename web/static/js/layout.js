// Every page: the side lists (active jobs with their stage, plates with their latest verdict) stay
// live, and the toolbar's "Log out" ends the dashboard session on the server.
import { refreshPartial } from "./api.js";

const side = document.getElementById("side");
const logout = document.getElementById("logout");
const POLL_MS = 2000;

const search = document.getElementById("plate-search");
const body = document.getElementById("side-body");
let page = 0; // the page of plates shown (0: the most recent); a new search starts again at 0

async function refresh() {
  try {
    const url = new URL(side.dataset.src, window.location.origin);
    if (search && search.value.trim()) url.searchParams.set("q", search.value.trim());
    if (page > 0) url.searchParams.set("page", String(page));
    await refreshPartial(body, url.pathname + url.search);
  } catch (err) {
    console.warn("side lists refresh failed:", err);
  }
}

if (side && body) {
  setInterval(refresh, POLL_MS);
  if (search) search.addEventListener("input", () => { page = 0; refresh(); });
  body.addEventListener("click", (event) => {
    const button = event.target.closest("[data-side-page]");
    if (!button) return;
    page = Number(button.dataset.sidePage);
    refresh();
  });
}

if (logout) {
  logout.addEventListener("click", async () => {
    await fetch("/api/v1/session", { method: "DELETE", credentials: "same-origin" });
    window.location.assign("/login");
  });
}
