// The bytes of a URL, or an Error naming what was fetched, where, and why it failed.
// Used by the page, the tile layer and the mesh worker (no DOM: a worker imports it too).

/** `Uint8Array` of `url`'s body; `what` names the file in the error ("the base patch"). */
export async function fetchBytes(url, what) {
  let response;
  try {
    response = await fetch(url);
  } catch (error) {
    throw new Error(`cannot fetch ${what} (${url}): ${error.message}`);
  }
  if (!response.ok) throw new Error(`cannot fetch ${what} (${url}): HTTP ${response.status}`);
  return new Uint8Array(await response.arrayBuffer());
}
