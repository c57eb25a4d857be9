// Cell page: capture a plate with the cell's cameras (the primary action; the page then follows the
// job to its result) or start one without them (simulated, uploaded bundle); the queue and the
// cameras' state stay live.
import { postForm, postJSON, refreshPartial, say } from "./api.js";

const form = document.getElementById("start-form");
const message = document.getElementById("start-message");
const queue = document.getElementById("queue");
const cameras = document.getElementById("cameras");
const captureButton = document.getElementById("capture");
const captureReason = document.getElementById("capture-reason");
const POLL_MS = 1000;
// The server checks the cameras at most every few seconds: no use asking more often.
const CAMERAS_POLL_MS = 5000;
let capturing = false;

function showSource() {
  const source = form.elements.source.value;
  for (const fieldset of form.querySelectorAll("[data-source]")) {
    fieldset.hidden = fieldset.dataset.source !== source;
  }
}

function number(name) {
  const value = form.elements[name].valueAsNumber;
  if (Number.isNaN(value)) throw new Error(`${name}: expected a number`);
  return value;
}

function simulationBody() {
  const body = {
    shape: form.elements.shape.value,
    radius_mm: number("radius_mm"),
    convex: form.elements.convex.value === "true",
    n_lights: number("n_lights"),
    lights: form.elements.lights.value,
    light_manifest: form.elements.light_manifest.value,
    noise: number("noise"),
    tolerance_mm: number("tolerance_mm"),
    width: number("width"),
    height: number("height"),
    seed: number("seed"),
    dents: [],
  };
  for (const name of ["floor_mm", "cutout_radius_mm"]) {
    if (form.elements[name].value !== "") body[name] = number(name);
  }
  if (form.elements.dent.checked) {
    body.dents.push({
      x_mm: number("dent_x_mm"),
      y_mm: number("dent_y_mm"),
      radius_mm: number("dent_radius_mm"),
      depth_mm: number("dent_depth_mm"),
    });
  }
  return body;
}

// The operator's name stays filled in on this screen (the cell's PC) from one plate to the next.
const OPERATOR_KEY = "plate-inspect.operator";
form.elements.operator.value = localStorage.getItem(OPERATOR_KEY) ?? "";

/** The operator's name as typed (remembered), or null when empty. */
function operatorName() {
  const name = form.elements.operator.value.trim();
  localStorage.setItem(OPERATOR_KEY, name);
  return name || null;
}

async function start(event) {
  event.preventDefault();
  const plateId = form.elements.plate_id.value.trim();
  const base = `/api/v1/plates/${encodeURIComponent(plateId)}/inspections`;
  const button = form.querySelector("button[type=submit]");
  button.disabled = true;
  say(message, "Sending…", "ok");
  try {
    let created;
    if (form.elements.source.value === "simulated") {
      const body = simulationBody();
      const operator = operatorName();
      if (operator) body.operator = operator;
      created = await postJSON(`${base}/simulated`, body);
    } else {
      const data = new FormData();
      // by its input: form.elements.capture also names the Capture button (its id)
      const bundles = [...form.querySelector("input[name=capture]").files]; // several: a plate's stations
      if (!bundles.length) throw new Error("capture: choose a bundle .zip");
      for (const bundle of bundles) data.append("capture", bundle);
      if (form.elements.target.files[0]) data.append("target", form.elements.target.files[0]);
      const operator = operatorName();
      if (operator) data.append("operator", operator);
      created = await postForm(base, data);
    }
    say(message, `Inspection #${created.id} queued.`, "ok");
    await refresh();
  } catch (err) {
    say(message, err.message, "error");
  } finally {
    button.disabled = false;
  }
}

async function capture() {
  const plateField = form.elements.plate_id;
  if (!plateField.reportValidity()) return;
  const plateId = plateField.value.trim();
  capturing = true;
  captureButton.disabled = true;
  say(message, "Sending…", "ok");
  try {
    const operator = operatorName();
    const created = await postJSON(
      `/api/v1/plates/${encodeURIComponent(plateId)}/inspections/acquire`, operator ? { operator } : {});
    say(message, `Inspection #${created.id} queued: the cell photographs plate ${plateId}.`, "ok");
    // Follow the job: its page shows the stage while it runs and the result once done.
    window.location.assign(`/inspections/${created.id}`);
  } catch (err) {
    say(message, err.message, "error");
    capturing = false;
    showCellStatus();
  }
}

// The Capture button follows the cell's state in the cameras panel (a cell config fixed or broken meanwhile).
function showCellStatus() {
  const status = cameras.querySelector(".cell-status");
  if (!status || capturing) return;
  const ready = status.dataset.ready === "true";
  captureButton.disabled = !ready;
  captureButton.title = ready ? "" : status.dataset.reason;
  captureReason.textContent = ready ? captureReason.dataset.help : `Capture unavailable: ${status.dataset.reason}`;
}

async function refreshCameras() {
  try {
    await refreshPartial(cameras, cameras.dataset.src);
    cameras.dataset.updated = String(Date.now());
    showCellStatus();
  } catch (err) {
    console.warn("cameras refresh failed:", err);
  }
}

async function refresh() {
  try {
    await refreshPartial(queue, queue.dataset.src);
    queue.dataset.updated = String(Date.now());
  } catch (err) {
    console.warn("queue refresh failed:", err);
  }
}

form.addEventListener("change", (event) => {
  if (event.target.name === "source") showSource();
});
form.addEventListener("submit", start);
captureButton.addEventListener("click", capture);
showSource();
setInterval(refresh, POLL_MS);
setInterval(refreshCameras, CAMERAS_POLL_MS);
