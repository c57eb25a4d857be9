// Calibration page: upload a stereo-calibration/1 file; it becomes the current one.
import { postForm, say } from "./api.js";

const form = document.getElementById("calibration-form");
const message = document.getElementById("calibration-message");

form.addEventListener("submit", async (event) => {
  event.preventDefault();
  const file = form.elements.calibration.files[0];
  if (!file) {
    say(message, "calibration: choose a JSON file", "error");
    return;
  }
  const data = new FormData();
  data.append("calibration", file);
  try {
    const created = await postForm("/api/v1/calibrations", data);
    say(message, `Calibration #${created.id} is now current (RMS ${created.rms_px ?? "—"} px).`, "ok");
    setTimeout(() => window.location.reload(), 800);
  } catch (err) {
    say(message, err.message, "error");
  }
});
