// Machines page: add a roll bender or replace one's geometry (PUT /api/v1/machines/{id}).
import { putJSON, say } from "./api.js";

const form = document.getElementById("machine-form");
const message = document.getElementById("machine-message");
const SIZES = ["bottom_roll_spacing_mm", "bottom_roll_diameter_mm", "top_roll_diameter_mm"];

form.addEventListener("submit", async (event) => {
  event.preventDefault();
  const id = form.elements.machine_id.value.trim();
  const body = { kind: "three-roll-pyramid" };
  for (const name of SIZES) body[name] = Number(form.elements[name].value);
  try {
    const saved = await putJSON(`/api/v1/machines/${encodeURIComponent(id)}`, body);
    say(message, `Machine ${saved.id} saved.`, "ok");
    setTimeout(() => window.location.assign("/machines"), 600);
  } catch (err) {
    say(message, err.message, "error");
  }
});
