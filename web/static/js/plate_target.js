// Plate page: the plate's cylinder target, its material and traceability (PUT /api/v1/plates/{id}/target).
import { putJSON, say } from "./api.js";

const form = document.getElementById("target-form");
const message = document.getElementById("target-message");

function text(name) {
  return form.elements[name].value.trim();
}

function targetDocument() {
  const doc = {
    format: "plate-target/1",
    shape: { type: "cylinder", radius_mm: Number(text("radius_mm")) },
    size_mm: [Number(text("width_mm")), Number(text("length_mm"))],
    tolerance_mm: Number(text("tolerance_mm")),
  };
  if (text("grade") || text("thickness_mm") || text("yield_mpa")) {
    doc.material = { grade: text("grade"), thickness_mm: Number(text("thickness_mm")), yield_mpa: Number(text("yield_mpa")) };
  }
  if (text("drawing_number")) doc.drawing = { number: text("drawing_number"), revision: text("drawing_revision") };
  for (const name of ["hull", "block"]) if (text(name)) doc[name] = text(name);
  return doc;
}

if (form) {
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    try {
      await putJSON(`/api/v1/plates/${encodeURIComponent(form.dataset.plate)}/target`, targetDocument());
      say(message, "Target saved.", "ok");
      setTimeout(() => window.location.reload(), 600);
    } catch (err) {
      say(message, err.message, "error");
    }
  });
}
