// Render the math of every page (pymdownx.arithmatex, generic mode) with the KaTeX bundled
// in docs/assets/katex: no CDN, so the built site works offline. Material's instant
// navigation swaps pages without a reload, hence document$.
function renderMath() {
  renderMathInElement(document.body, {
    delimiters: [
      { left: "$$", right: "$$", display: true },
      { left: "\\[", right: "\\]", display: true },
      { left: "\\(", right: "\\)", display: false },
    ],
    throwOnError: false,
  });
}
if (typeof document$ !== "undefined") {
  document$.subscribe(renderMath);
} else {
  document.addEventListener("DOMContentLoaded", renderMath);
}
