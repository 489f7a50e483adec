// admin-resumable-upload.js and admin-upload-rate.js: chunks at the server's offsets, a
// connection dropped mid-chunk resumed from HEAD's offset, a reload resumed from storage,
// refusals not retried, a bounded number of retries; rate and time left from the samples.

import assert from "node:assert/strict";
import { test } from "node:test";

import { ResumableUpload, UploadFailure } from "../src/admin-resumable-upload.js";
import { UploadRate, formatBytes, formatDuration } from "../src/admin-upload-rate.js";

/** An in-memory server of the tus core protocol, with scripted failures: `script[n]` is
 *  what the n-th PATCH does ({drop: bytes kept before the connection dies} or {status}). */
class FakeTusServer {
  constructor({ script = {}, createStatus = 201, headDown = 0 } = {}) {
    Object.assign(this, { script, createStatus, headDown });
    this.uploads = new Map();
    this.log = [];
    this.patches = 0;
    this.fitted = null;
  }

  answer(status, headers = {}, body = null) {
    return { status, body, header: (name) => headers[name] ?? null };
  }

  async request({ method, url, headers, body, onProgress }) {
    this.log.push(`${method} ${url}${headers["Upload-Offset"] ? ` @${headers["Upload-Offset"]}` : ""}`);
    if (method === "POST" && url === "/api/resumable") {
      if (this.createStatus !== 201) return this.answer(this.createStatus, {}, { error: "too large" });
      const id = `/api/resumable/${this.uploads.size + 1}`;
      this.uploads.set(id, { length: Number(headers["Upload-Length"]), data: [], fields: body,
                             name: new TextDecoder().decode(Uint8Array.from(
                               atob(headers["Upload-Metadata"].split(" ")[1]), (c) => c.charCodeAt(0))) });
      return this.answer(201, { Location: id });
    }
    const upload = this.uploads.get(url.replace(/\/fit$/, ""));
    if (!upload) return this.answer(404, {}, { error: "no such upload" });
    if (method === "HEAD") {
      if (this.headDown > 0) {
        this.headDown -= 1;
        return { status: 0, header: () => null, body: null, error: "offline" };
      }
      return this.answer(200, { "Upload-Offset": String(upload.data.length),
                                "Upload-Length": String(upload.length) });
    }
    if (method === "PATCH") {
      const offset = Number(headers["Upload-Offset"]);
      if (offset !== upload.data.length) return this.answer(409, {}, { error: "wrong offset" });
      const step = this.script[this.patches++] || {};
      if (step.status) return this.answer(step.status, {}, { error: `scripted ${step.status}` });
      const kept = step.drop ?? body.length;
      upload.data.push(...body.subarray(0, kept));
      onProgress?.(kept);
      if (step.drop !== undefined) return { status: 0, header: () => null, body: null, error: "dropped" };
      return this.answer(204, { "Upload-Offset": String(upload.data.length) });
    }
    if (method === "POST" && url.endsWith("/fit")) {
      if (upload.data.length !== upload.length) return this.answer(409, {}, { error: "unfinished" });
      this.fitted = { bytes: Uint8Array.from(upload.data), fields: body, name: upload.name };
      return this.answer(202, {}, { job: 7, object: "relief", job_url: "/api/jobs/7" });
    }
    return this.answer(405);
  }
}

class MemoryStorage {
  constructor(items = {}) { this.items = new Map(Object.entries(items)); }
  getItem(k) { return this.items.has(k) ? this.items.get(k) : null; }
  setItem(k, v) { this.items.set(k, String(v)); }
  removeItem(k) { this.items.delete(k); }
}

const FILE_BYTES = Uint8Array.from({ length: 100 }, (_, i) => (i * 7) % 256);
const scanFile = () => new File([FILE_BYTES], "relief ü.ply", { lastModified: 1234 });

function uploader(server, extra = {}) {
  const waits = [];
  const progress = [];
  const upload = new ResumableUpload({
    endpoint: "/api/resumable", file: scanFile(), fields: { grid: "12x12" },
    headers: { "X-CSRF-Token": "t" }, transport: server, storage: extra.storage || new MemoryStorage(),
    chunkBytes: 30, sleep: async (ms) => { waits.push(ms); }, onProgress: (p) => progress.push(p.sent),
    ...extra,
  });
  return { upload, waits, progress };
}

test("the file goes in chunks at the server's offsets, then to the fit with the fields", async () => {
  const server = new FakeTusServer();
  const { upload, progress } = uploader(server);
  const job = await upload.run();
  assert.deepEqual(job, { job: 7, object: "relief", job_url: "/api/jobs/7" });
  assert.deepEqual(server.log, ["POST /api/resumable", "PATCH /api/resumable/1 @0",
    "PATCH /api/resumable/1 @30", "PATCH /api/resumable/1 @60", "PATCH /api/resumable/1 @90",
    "POST /api/resumable/1/fit"]);
  assert.deepEqual(server.fitted.bytes, FILE_BYTES);
  assert.equal(server.fitted.fields, "grid=12x12");
  assert.equal(server.fitted.name, "relief ü.ply"); // Upload-Metadata: base64 of UTF-8
  assert.equal(progress.at(-1), 100);
  assert.equal(upload.storage.getItem(upload.key), null); // done: nothing left to resume
});

test("a connection dropped mid-chunk resumes from the offset HEAD gives", async () => {
  const server = new FakeTusServer({ script: { 1: { drop: 12 } } });
  const { upload, waits } = uploader(server);
  await upload.run();
  assert.deepEqual(server.fitted.bytes, FILE_BYTES);
  assert.deepEqual(waits, [1000]);
  assert.deepEqual(server.log.slice(2, 6), ["PATCH /api/resumable/1 @30", "HEAD /api/resumable/1",
    "PATCH /api/resumable/1 @42", "PATCH /api/resumable/1 @72"]);
});

test("failures back off 1, 2, 4 s, a busy or offline server included, then give up", async () => {
  const busy = new FakeTusServer({ script: { 0: { status: 503 }, 1: { status: 409 } }, headDown: 1 });
  const first = uploader(busy);
  await first.upload.run();
  assert.deepEqual(first.waits, [1000, 2000]);
  assert.deepEqual(busy.fitted.bytes, FILE_BYTES);

  const script = Object.fromEntries(Array.from({ length: 10 }, (_, i) => [i, { status: 502 }]));
  const down = new FakeTusServer({ script });
  const second = uploader(down, { maxFailures: 3 });
  await assert.rejects(second.upload.run(), (e) => e instanceof UploadFailure
    && /stopped after 3 failed attempts/.test(e.message));
  assert.deepEqual(second.waits, [1000, 2000, 4000]);
  // the URL stays, so the same file picked again resumes
  assert.equal(second.upload.storage.getItem(second.upload.key), "/api/resumable/1");
});

test("a refusal is not retried and says the server's message", async () => {
  const server = new FakeTusServer({ createStatus: 413 });
  const { upload, waits } = uploader(server);
  await assert.rejects(upload.run(), { name: "UploadFailure", message: "too large", status: 413 });
  assert.deepEqual(waits, []);
});

test("after a reload the same file resumes from the stored upload; a stale one starts anew", async () => {
  const server = new FakeTusServer();
  const storage = new MemoryStorage();
  const interrupted = uploader(server, { storage, maxFailures: 0,
                                         transport: { request: (r) => r.method === "PATCH"
                                           && r.headers["Upload-Offset"] === "60"
                                           ? { status: 0, header: () => null, body: null }
                                           : server.request(r) } });
  await assert.rejects(interrupted.upload.run(), UploadFailure);
  assert.equal(server.uploads.get("/api/resumable/1").data.length, 60);
  server.log = [];
  const again = uploader(server, { storage }); // a new page, the same file picked again
  await again.upload.run();
  assert.equal(again.upload.resumed, true);
  assert.deepEqual(server.log, ["HEAD /api/resumable/1", "PATCH /api/resumable/1 @60",
    "PATCH /api/resumable/1 @90", "POST /api/resumable/1/fit"]);
  assert.deepEqual(server.fitted.bytes, FILE_BYTES);

  const stale = new MemoryStorage({ [again.upload.key]: "/api/resumable/99" });
  const fresh = new FakeTusServer();
  await uploader(fresh, { storage: stale }).upload.run();
  assert.deepEqual(fresh.log.slice(0, 2), ["HEAD /api/resumable/99", "POST /api/resumable"]);
});

test("rate and time left come from the last samples; sizes and durations read well", () => {
  let now = 0;
  const rate = new UploadRate(10_000, () => now);
  rate.add(0);
  assert.equal(rate.rate(), null);
  for (let s = 1; s <= 20; s++) {
    now = s * 1000;
    rate.add(s <= 10 ? s * 1_000_000 : 10_000_000 + (s - 10) * 2_000_000);
  }
  assert.equal(rate.rate(), 2_000_000); // the window holds the last 10 s only
  assert.equal(rate.eta(40_000_000), 5);
  assert.equal(formatBytes(512), "512 B");
  assert.equal(formatBytes(3.5 * 2 ** 20), "3.50 MiB");
  assert.equal(formatBytes(3 * 2 ** 30 * 1.05), "3.15 GiB");
  assert.equal(formatDuration(45), "45 s");
  assert.equal(formatDuration(725), "12 min 5 s");
  assert.equal(formatDuration(7380), "2 h 3 min");
});
