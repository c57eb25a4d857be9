// Result page: the plate map (templates placed by a click on it), the templates at another spacing,
// and a live status while the job runs.
import { getJSON, refreshPartial } from "./api.js";
import { PlateMap } from "./plate_map.js";

const spacing = document.getElementById("spacing");
const templates = document.getElementById("templates");
const watch = document.querySelector("[data-watch]");
const mapFigure = document.getElementById("plate-map");
const POLL_MS = 1000;

const here = new URL(window.location.href);
const chosen = () => {
  const x = here.searchParams.get("at_x"), y = here.searchParams.get("at_y");
  return x !== null && y !== null ? [Number(x), Number(y)] : null;
};

/** The template frames as drawn on the map, read from the templates' figures. */
function frameLines() {
  if (!templates) return [];
  return [...templates.querySelectorAll("figure[data-line]")].map((figure) => {
    const [x1, y1, x2, y2] = figure.dataset.line.split(" ").map(Number);
    const kind = figure.dataset.kind;
    const label = kind === "defect" ? `T${figure.dataset.defect}` : kind === "chosen" ? "yours" : "";
    return { x1, y1, x2, y2, kind, label };
  });
}

let map = null;

async function reloadTemplates() {
  const url = new URL(templates.dataset.src, window.location.origin);
  for (const key of ["spacing_mm", "at_x", "at_y"]) {
    const value = here.searchParams.get(key);
    if (value !== null) url.searchParams.set(key, value);
  }
  templates.setAttribute("aria-busy", "true");
  try {
    await refreshPartial(templates, url.pathname + url.search);
    window.history.replaceState(null, "", here);
    map?.setFrames(frameLines());
  } finally {
    templates.removeAttribute("aria-busy");
  }
}

if (spacing && templates) {
  spacing.addEventListener("change", () => {
    here.searchParams.set("spacing_mm", spacing.value);
    reloadTemplates();
  });
}

if (mapFigure) {
  map = new PlateMap(mapFigure, {
    onPick: async ([x, y]) => {
      here.searchParams.set("at_x", x.toFixed(0));
      here.searchParams.set("at_y", y.toFixed(0));
      map.setPicked([Math.round(x), Math.round(y)]);
      await reloadTemplates();
      mapFigure.querySelector(".map-readout").textContent =
        `A template now goes through x ${x.toFixed(0)} mm, y ${y.toFixed(0)} mm: see "Virtual templates" below.`;
    },
  });
  map.load().then(() => {
    map.setFrames(frameLines());
    map.setPicked(chosen());
  }).catch((err) => {
    mapFigure.querySelector(".map-readout").textContent = `The map could not be drawn: ${err.message}`;
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
