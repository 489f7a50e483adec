// ResumableUpload: one file sent to the admin's resumable upload API in chunks, resumed
// from the server's offset after a dropped connection or a reload, then submitted for a fit.
//
// The protocol is the tus resumable upload protocol 1.0.0 (https://tus.io/protocols/
// resumable-upload; fitter/collection/resumable.py is the server): POST creates the
// upload with its size (`Upload-Length`) and the file's name (`Upload-Metadata`), HEAD
// answers the server's offset, PATCH sends the bytes at `Upload-Offset`, each chunk with
// its SHA-256 (`Upload-Checksum`, where the browser has WebCrypto); then POST `<url>/fit`.
//
// What the server holds is always a prefix of the file, so after any failure (no answer,
// a 5xx, a 409 from a writer still busy or an offset that moved) the client waits
// (1, 2, 4 ... 30 s), asks HEAD for the offset and goes on from there. The upload's URL is
// kept in `storage` (localStorage) under the file's name, size and modification time, so
// the same file picked again after a reload resumes instead of starting over.
// I/O is injected (`transport`, `storage`, `sleep`, `digest`), so node tests it whole.

import { UploadRate } from "./admin-upload-rate.js";

const TUS_VERSION = "1.0.0";
/** statuses after which the client waits, asks the offset and tries again (0: no answer) */
export const RETRY_STATUSES = new Set([0, 408, 409, 423, 429, 460, 500, 502, 503, 504]);
/** statuses after which the server will never take this upload: forget its URL */
const GONE_STATUSES = new Set([404, 410, 413, 422]);

export class UploadFailure extends Error {
  constructor(message, status) {
    super(message);
    this.name = "UploadFailure";
    this.status = status;
  }
}

/** SHA-256 of `bytes` as base64 (WebCrypto), or null where there is none (plain HTTP). */
export async function sha256Base64(bytes) {
  const subtle = globalThis.crypto?.subtle;
  if (!subtle) return null;
  const digest = new Uint8Array(await subtle.digest("SHA-256", bytes));
  return btoa(String.fromCharCode(...digest));
}

function base64Text(text) {
  const bytes = new TextEncoder().encode(text);
  let binary = "";
  for (const b of bytes) binary += String.fromCharCode(b);
  return btoa(binary);
}

function messageOf(response) {
  if (response.body && response.body.error) return response.body.error;
  if (response.status === 0) return response.error || "no answer from the server";
  return `the server answered ${response.status}`;
}

export class ResumableUpload {
  /**
   * @param {object} o
   * @param {string} o.endpoint  the creation URL (/admin/api/uploads/resumable)
   * @param {File} o.file
   * @param {Object<string,string>} o.fields  fit options and title, sent at creation and fit
   * @param {Object<string,string>} o.headers  sent on every request (X-CSRF-Token)
   * @param {{request: Function}} o.transport  request({method, url, headers, body,
   *   onProgress}) -> Promise<{status, header(name), body, error}>; status 0: no answer
   * @param {Storage} o.storage  where the upload's URL is kept (localStorage)
   */
  constructor({ endpoint, file, fields = {}, headers = {}, transport, storage,
                chunkBytes = 8 << 20, maxFailures = 8, maxWaitMs = 30_000,
                sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms)),
                digest = sha256Base64, rate = new UploadRate(),
                onProgress = () => {}, onRetry = () => {} }) {
    Object.assign(this, { endpoint, file, fields, headers, transport, storage, chunkBytes,
                          maxFailures, maxWaitMs, sleep, digest, rate, onProgress, onRetry });
    this.url = null;
    this.offset = 0;
    this.failures = 0;
    this.resumed = false;
  }

  /** The localStorage key of this file: its name, size and modification time. */
  get key() {
    return `tessera-upload:${this.file.name}:${this.file.size}:${this.file.lastModified}`;
  }

  /** Send the file and queue its fit: the fit's JSON ({job, object, job_url}).
   *  @throws {UploadFailure} a refusal, or too many failures in a row */
  async run() {
    this.url = (await this.resume()) || (await this.create());
    this.rate.reset();
    this.report(this.offset);
    while (this.offset < this.file.size) await this.sendChunk();
    return this.submit();
  }

  request(method, url, extra = {}, body = null, onProgress = undefined) {
    return this.transport.request({ method, url, body, onProgress,
                                    headers: { ...this.headers, "Tus-Resumable": TUS_VERSION,
                                               ...extra } });
  }

  /** The stored upload of this file, if the server still has it (then `offset` is set). */
  async resume() {
    const url = this.storage.getItem(this.key);
    if (!url) return null;
    const head = await this.request("HEAD", url);
    if (head.status === 200 && Number(head.header("Upload-Length")) === this.file.size) {
      this.offset = Number(head.header("Upload-Offset"));
      this.resumed = true;
      return url;
    }
    if (!GONE_STATUSES.has(head.status)) {
      throw new UploadFailure(`cannot reach the unfinished upload: ${messageOf(head)}`,
                              head.status);
    }
    this.storage.removeItem(this.key);
    return null;
  }

  async create() {
    const response = await this.request("POST", this.endpoint, {
      "Upload-Length": String(this.file.size),
      "Upload-Metadata": `filename ${base64Text(this.file.name)}`,
      "Content-Type": "application/x-www-form-urlencoded",
    }, new URLSearchParams(this.fields).toString());
    if (response.status !== 201) throw new UploadFailure(messageOf(response), response.status);
    const url = response.header("Location");
    this.storage.setItem(this.key, url);
    this.offset = 0;
    return url;
  }

  async sendChunk() {
    const start = this.offset;
    const end = Math.min(start + this.chunkBytes, this.file.size);
    const bytes = new Uint8Array(await this.file.slice(start, end).arrayBuffer());
    const extra = { "Upload-Offset": String(start),
                    "Content-Type": "application/offset+octet-stream" };
    const checksum = this.digest ? await this.digest(bytes) : null;
    if (checksum) extra["Upload-Checksum"] = `sha256 ${checksum}`;
    const response = await this.request("PATCH", this.url, extra, bytes,
                                        (sent) => this.report(start + sent));
    if (response.status === 204) {
      this.offset = Number(response.header("Upload-Offset"));
      this.failures = 0;
      this.report(this.offset);
      return;
    }
    await this.recover(response);
  }

  /** After a failed request: give up on a refusal, else wait and take the server's offset. */
  async recover(response) {
    const reason = messageOf(response);
    if (!RETRY_STATUSES.has(response.status)) {
      if (GONE_STATUSES.has(response.status)) this.storage.removeItem(this.key);
      throw new UploadFailure(reason, response.status);
    }
    this.failures += 1;
    if (this.failures > this.maxFailures) {
      throw new UploadFailure(`stopped after ${this.maxFailures} failed attempts in a row ` +
                              `(${reason}); pick the same file again to resume`, response.status);
    }
    const wait = Math.min(1000 * 2 ** (this.failures - 1), this.maxWaitMs);
    this.onRetry({ attempt: this.failures, waitMs: wait, reason });
    await this.sleep(wait);
    this.rate.reset();
    const head = await this.request("HEAD", this.url);
    if (head.status === 200) {
      this.offset = Number(head.header("Upload-Offset"));
      this.report(this.offset);
    } else if (GONE_STATUSES.has(head.status)) {
      this.storage.removeItem(this.key);
      throw new UploadFailure("the server no longer has this upload (expired or deleted); " +
                              "start again", head.status);
    } // else still no answer: the next PATCH at the old offset fails or succeeds
  }

  async submit() {
    for (;;) {
      const response = await this.request("POST", `${this.url}/fit`, {
        "Content-Type": "application/x-www-form-urlencoded",
      }, new URLSearchParams(this.fields).toString());
      if (response.status === 202) {
        this.storage.removeItem(this.key);
        return response.body;
      }
      if (response.status !== 0) {
        if (GONE_STATUSES.has(response.status)) this.storage.removeItem(this.key);
        throw new UploadFailure(messageOf(response), response.status);
      }
      await this.recover(response); // no answer: wait, then ask again
    }
  }

  report(sent) {
    this.rate.add(sent);
    this.onProgress({ sent, total: this.file.size, rate: this.rate.rate(),
                      eta: this.rate.eta(this.file.size), resumed: this.resumed });
  }
}
