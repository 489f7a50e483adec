// XhrTransport: the browser's requests for ResumableUpload, by XMLHttpRequest because only
// its `upload.onprogress` reports the bytes of a request body as they leave (fetch does not).
// Every outcome resolves: a failed connection is status 0 with a message, never a throw.

export class XhrTransport {
  /** @param {string} base  the URL relative URLs are resolved against (the page's) */
  constructor(base = document.baseURI) {
    this.base = base;
    this.current = null;
  }

  request({ method, url, headers = {}, body = null, onProgress }) {
    return new Promise((resolve) => {
      const xhr = new XMLHttpRequest();
      this.current = xhr;
      xhr.open(method, new URL(url, this.base).href);
      for (const [name, value] of Object.entries(headers)) xhr.setRequestHeader(name, value);
      if (body !== null && onProgress) xhr.upload.onprogress = (e) => onProgress(e.loaded);
      xhr.onload = () => {
        let parsed = null;
        try {
          parsed = xhr.responseText ? JSON.parse(xhr.responseText) : null;
        } catch {
          parsed = null; // not JSON (a proxy's error page): the status says enough
        }
        resolve({ status: xhr.status, header: (name) => xhr.getResponseHeader(name),
                  body: parsed });
      };
      const failed = (what) => () => resolve({ status: 0, header: () => null, body: null,
                                               error: what });
      xhr.onerror = failed("the connection failed");
      xhr.ontimeout = failed("the request timed out");
      xhr.onabort = failed("the request was stopped");
      xhr.send(body);
    });
  }

  /** Stop the request in flight (it resolves with status 0). */
  abort() {
    this.current?.abort();
  }
}
