// Logging in: the key is checked with GET /api/v1/whoami before it is kept (in this tab's
// sessionStorage); a wrong key is refused with a message and nothing is kept.

import { api, ApiError, describe, storeKey } from "../api.js";
import { h, replace } from "../dom.js";

/** Show the login form in `main`; resolves with {who} once a valid key was given. */
export function showLogin(main, message = "") {
  return new Promise((resolve) => {
    const input = h("input", {
      id: "login-key", type: "password", name: "key", autocomplete: "off", spellcheck: "false", required: true,
      "aria-describedby": "login-help login-error",
    });
    const error = h("p", { id: "login-error", class: "error", role: "alert" }, message);
    const button = h("button", { type: "submit", class: "primary" }, "Log in");
    const form = h("form", { class: "login card", "aria-labelledby": "login-title" },
      h("h1", { id: "login-title" }, "cell: operator's page"),
      h("label", { for: "login-key" }, "API key"),
      input,
      h("p", { id: "login-help", class: "hint" },
        "A key made with ", h("code", { class: "mono" }, "cell keys create"),
        ". It is kept in this browser tab only, until you log out or close the tab."),
      button, error);
    form.addEventListener("submit", async (event) => {
      event.preventDefault();
      const key = input.value.trim();
      button.disabled = true;
      error.textContent = "";
      try {
        const who = await api("/api/v1/whoami", { key });
        storeKey(key);
        resolve({ who });
      } catch (failure) {
        error.textContent = failure instanceof ApiError && failure.status === 401
          ? "This key is not valid: the cell does not know it, or it was revoked."
          : `Could not log in: ${describe(failure)}`;
        input.select();
      } finally {
        button.disabled = false;
      }
    });
    replace(main, form);
    input.focus();
  });
}
