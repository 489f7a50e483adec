// UploadRate: the rate of an upload and the time it still needs, from the bytes sent so far.
//
//   rate = (bytes_now - bytes_then) / (t_now - t_then)   over the last `windowMs` of samples,
//   eta  = (total - bytes_now) / rate
//
// A sliding window follows a network that speeds up or slows down within seconds, and a
// resumed upload's bytes sent before the page loaded never count as sent at once.

export class UploadRate {
  /** @param {number} windowMs  how far back the rate looks; @param {() => number} now  ms */
  constructor(windowMs = 10_000, now = () => performance.now()) {
    this.windowMs = windowMs;
    this.now = now;
    this.samples = []; // [{t, bytes}], oldest first
  }

  /** Note that `bytes` of the file are on the server (or on their way) now. */
  add(bytes) {
    const t = this.now();
    this.samples.push({ t, bytes });
    while (this.samples.length > 2 && this.samples[0].t < t - this.windowMs) this.samples.shift();
  }

  /** Forget the samples (after a pause or a dropped connection: the wait is not a rate). */
  reset() {
    this.samples = [];
  }

  /** Bytes per second, or null before a quarter of a second of samples. */
  rate() {
    if (this.samples.length < 2) return null;
    const first = this.samples[0];
    const last = this.samples[this.samples.length - 1];
    const seconds = (last.t - first.t) / 1000;
    return seconds >= 0.25 ? Math.max(0, last.bytes - first.bytes) / seconds : null;
  }

  /** Seconds left to send `total` bytes at the current rate, or null when unknown. */
  eta(total) {
    const rate = this.rate();
    if (!rate) return null;
    return Math.max(0, total - this.samples[this.samples.length - 1].bytes) / rate;
  }
}

/** `n` bytes for people: "512 B", "3.5 MiB", "2.87 GiB". */
export function formatBytes(n) {
  const units = ["B", "KiB", "MiB", "GiB", "TiB"];
  let unit = 0;
  while (n >= 1024 && unit < units.length - 1) {
    n /= 1024;
    unit += 1;
  }
  return unit === 0 ? `${n} B` : `${n.toFixed(n < 10 ? 2 : 1)} ${units[unit]}`;
}

/** `seconds` for people: "45 s", "12 min 5 s", "2 h 3 min". */
export function formatDuration(seconds) {
  const s = Math.round(seconds);
  if (s < 60) return `${s} s`;
  if (s < 3600) return `${Math.floor(s / 60)} min ${s % 60} s`;
  return `${Math.floor(s / 3600)} h ${Math.floor((s % 3600) / 60)} min`;
}
