// Every page: the side lists (active jobs with their stage, plates with their latest verdict) stay
// live, and the toolbar's "Log out" ends the dashboard session on the server.
import { refreshPartial } from "./api.js";

const side = document.getElementById("side");
const logout = document.getElementById("logout");
const POLL_MS = 2000;

async function refresh() {
  try {
    await refreshPartial(side, side.dataset.src);
  } catch (err) {
    console.warn("side lists refresh failed:", err);
  }
}

if (side) setInterval(refresh, POLL_MS);

if (logout) {
  logout.addEventListener("click", async () => {
    await fetch("/api/v1/session", { method: "DELETE", credentials: "same-origin" });
    window.location.assign("/login");
  });
}
