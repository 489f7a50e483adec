// The admin upload page: the form's scan goes to the resumable upload API in chunks
// (ResumableUpload), with a progress bar, bytes, rate and time left; a dropped connection is
// retried from the server's offset, and after a reload the same file picked again resumes.
// Without JavaScript the form still posts the whole file in one request. URLs and the chunk
// size come from the page's JSON config (`upload-config`).

import { ResumableUpload } from "./admin-resumable-upload.js";
import { formatBytes, formatDuration } from "./admin-upload-rate.js";
import { XhrTransport } from "./admin-xhr-transport.js";

/** form fields that are not fit options (the file, and the CSRF token sent as a header) */
const NOT_OPTIONS = new Set(["scan", "csrf_token"]);

export class UploadPage {
  constructor(config, doc = document, storage = window.localStorage) {
    this.config = config;
    this.storage = storage;
    this.transport = new XhrTransport(doc.baseURI);
    const byId = (id) => doc.getElementById(id);
    this.el = {
      form: byId("upload-form"), file: doc.querySelector("#upload-form input[name=scan]"),
      button: doc.querySelector("#upload-form button[type=submit]"),
      progress: byId("upload-progress"), bar: byId("upload-bar"), status: byId("upload-status"),
      retry: byId("upload-retry"), error: byId("upload-error"),
      unfinished: byId("upload-unfinished"), unfinishedList: byId("upload-unfinished-list"),
    };
    this.csrf = this.el.form.querySelector("input[name=csrf_token]").value;
  }

  start() {
    this.el.form.addEventListener("submit", (event) => {
      event.preventDefault();
      this.upload();
    });
    this.showUnfinished();
  }

  /** The fit options and title of the form (empty fields keep their defaults). */
  fields() {
    const fields = {};
    for (const [name, value] of new FormData(this.el.form)) {
      if (!NOT_OPTIONS.has(name) && typeof value === "string" && value.trim()) {
        fields[name] = value;
      }
    }
    return fields;
  }

  async upload() {
    const file = this.el.file.files[0];
    if (!file) return;
    this.el.button.disabled = true;
    this.el.error.hidden = true;
    this.el.progress.hidden = false;
    const upload = new ResumableUpload({
      endpoint: this.config.endpoint, file, fields: this.fields(), storage: this.storage,
      headers: { "X-CSRF-Token": this.csrf }, transport: this.transport,
      chunkBytes: this.config.chunk_bytes,
      onProgress: (p) => this.showProgress(p),
      onRetry: (r) => this.showRetry(r),
    });
    try {
      const job = await upload.run();
      this.el.status.textContent = "Uploaded; the fit is queued.";
      window.location.assign(`${this.config.jobs_page}/${job.job}`);
    } catch (error) {
      this.el.error.textContent = `The upload stopped: ${error.message}`;
      this.el.error.hidden = false;
      this.el.retry.hidden = true;
      this.el.button.disabled = false;
      this.el.button.textContent = "Resume the upload";
    }
  }

  showProgress({ sent, total, rate, eta, resumed }) {
    this.el.retry.hidden = true;
    this.el.bar.value = total ? sent / total : 0;
    this.el.progress.dataset.sent = String(sent);
    const parts = [`${formatBytes(sent)} of ${formatBytes(total)}`];
    if (rate) parts.push(`${formatBytes(rate)}/s`);
    if (eta !== null && sent < total) parts.push(`${formatDuration(eta)} left`);
    if (resumed) parts.push("resumed");
    this.el.status.textContent = parts.join(" · ");
  }

  showRetry({ attempt, waitMs, reason }) {
    const said = reason.charAt(0).toUpperCase() + reason.slice(1);
    this.el.retry.textContent = `${said}; retrying in ${Math.round(waitMs / 1000)} s ` +
                                `(attempt ${attempt}).`;
    this.el.retry.hidden = false;
    this.el.progress.dataset.retries = String(attempt);
  }

  /** The server's unfinished uploads: the admin picks the same file again to resume one. */
  async showUnfinished() {
    const response = await this.transport.request({ method: "GET", url: this.config.endpoint,
                                                    headers: { Accept: "application/json" } });
    const open = (response.body?.uploads || []).filter((u) => !u.complete);
    if (response.status !== 200 || !open.length) return;
    this.el.unfinishedList.replaceChildren(...open.map((u) => {
      const item = document.createElement("li");
      item.textContent = `${u.filename || "(no name)"}: ${formatBytes(u.offset)} of ` +
                         `${formatBytes(u.length)}, kept until ` +
                         `${new Date(u.expires * 1000).toLocaleString()}`;
      return item;
    }));
    this.el.unfinished.hidden = false;
  }
}

const configElement = document.getElementById("upload-config");
if (configElement) new UploadPage(JSON.parse(configElement.textContent)).start();
