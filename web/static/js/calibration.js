// Calibration page: upload a stereo-calibration/1 or a light-calibration/1 file; it becomes the current one.
import { postForm, say } from "./api.js";

function wireUpload(formId, messageId, url, describe) {
  const form = document.getElementById(formId);
  const message = document.getElementById(messageId);
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
      const created = await postForm(url, data);
      say(message, describe(created), "ok");
      setTimeout(() => window.location.reload(), 800);
    } catch (err) {
      say(message, err.message, "error");
    }
  });
}

wireUpload("calibration-form", "calibration-message", "/api/v1/calibrations",
  (created) => `Calibration #${created.id} is now current (RMS ${created.rms_px ?? "—"} px).`);
wireUpload("light-calibration-form", "light-calibration-message", "/api/v1/light-calibrations",
  (created) => `Light calibration #${created.id} (${created.n_lights} lights) is now current.`);
