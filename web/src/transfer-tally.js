// TransferTally: what a visit transferred and what the object costs, from Resource Timing
// entries (the page's own, and the mesh worker's, which only the worker can read).
//
//   transferred = Σ transferSize over every entry (headers included; 0 when the browser's
//                 cache answered), split into "runtime" (the page, its modules, Pyodide,
//                 three.js, client_py) and "object" (files under the bundle's folder)
//   object cost = Σ encodedBodySize over the bundle's files seen (manifest as served, patch,
//                 the detail and texture tiles of the levels shown), cached or not
//
// A URL seen twice (the page and the worker, or a refetch) counts once for the cost and at
// every transfer. Entries of a cross-origin server without Timing-Allow-Origin report 0.

export class TransferTally {
  /** @param {string} bundleUrl  the bundle's folder (its manifest's URL minus the file name),
   *  absolute or relative to `base`; @param {string} base  the page's URL */
  constructor(bundleUrl, base) {
    this.bundlePrefix = new URL(bundleUrl.replace(/[^/]*$/, ""), base).href;
    this.entries = new Map(); // source -> entries, replaced whole by each add()
  }

  /** Take the entries of one timeline (`source`: "page" or "worker"), replacing its last. */
  add(source, entries) {
    this.entries.set(source, entries.map(({ name, transferSize, encodedBodySize }) => ({
      name, transferSize: transferSize || 0, encodedBodySize: encodedBodySize || 0 })));
  }

  /** {runtime, object, total: bytes transferred; objectCost: bytes of the object as served;
   *  requests: entries; cached: entries answered by the browser's cache} */
  summary() {
    let runtime = 0;
    let object = 0;
    let requests = 0;
    let cached = 0;
    const cost = new Map();
    for (const entries of this.entries.values()) {
      for (const entry of entries) {
        requests += 1;
        if (entry.transferSize === 0) cached += 1;
        if (entry.name.startsWith(this.bundlePrefix)) {
          object += entry.transferSize;
          cost.set(entry.name, Math.max(cost.get(entry.name) || 0, entry.encodedBodySize));
        } else {
          runtime += entry.transferSize;
        }
      }
    }
    const objectCost = [...cost.values()].reduce((sum, n) => sum + n, 0);
    return { runtime, object, total: runtime + object, objectCost, requests, cached };
  }
}
