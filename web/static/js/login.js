// Login page: trade the API token for the dashboard's session cookie.
import { postJSON, say } from "./api.js";

const form = document.getElementById("login-form");
const message = document.getElementById("login-message");

form.addEventListener("submit", async (event) => {
  event.preventDefault();
  try {
    await postJSON("/api/v1/session", { token: form.elements.token.value });
    form.reset();
    window.location.assign("/cell");
  } catch (err) {
    say(message, err.message, "error");
  }
});
