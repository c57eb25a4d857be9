// Result page: the templates at another spacing, and a live status while the job runs.
import { getJSON, refreshPartial } from "./api.js";

const spacing = document.getElementById("spacing");
const templates = document.getElementById("templates");
const watch = document.querySelector("[data-watch]");
const POLL_MS = 1000;

if (spacing && templates) {
  spacing.addEventListener("change", async () => {
    const url = `${templates.dataset.src}?spacing_mm=${encodeURIComponent(spacing.value)}`;
    templates.setAttribute("aria-busy", "true");
    try {
      await refreshPartial(templates, url);
      const next = new URL(window.location.href);
      next.searchParams.set("spacing_mm", spacing.value);
      window.history.replaceState(null, "", next);
    } finally {
      templates.removeAttribute("aria-busy");
    }
  });
}

async function poll() {
  try {
    const job = await getJSON(watch.dataset.watch);
    document.getElementById("live-status").textContent = job.status.toUpperCase();
    watch.dataset.status = job.status;
    document.getElementById("live-stage").textContent = job.stage ?? job.status;
    document.getElementById("live-progress").value = job.progress;
    if (job.status === "done" || job.status === "error") {
      window.location.reload();
      return;
    }
  } catch (err) {
    console.warn("status poll failed:", err);
  }
  setTimeout(poll, POLL_MS);
}

if (watch) poll();
