// The gallery: a card whose thumbnail cannot be loaded shows its "No preview" note instead.
// (A module rather than an onerror attribute: the Content-Security-Policy runs no inline
// handlers.) A thumbnail may have failed before this module runs: `complete` with no width.

for (const img of document.querySelectorAll(".card .thumb img")) {
  const showMissing = () => img.parentElement.classList.add("missing");
  if (img.complete && img.naturalWidth === 0) showMissing();
  else img.addEventListener("error", showMissing);
}
