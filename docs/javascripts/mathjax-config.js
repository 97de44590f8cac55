// MathJax 2 configuration for the Markdown pages (pymdownx.arithmatex writes \( \) and \[ \]).
// MathJax itself is served from this site (assets/mathjax, copied by docs/hooks.py from the
// jupyter-server-mathjax package): no CDN. A notebook page loads MathJax with its own
// configuration first; then this one stands aside.
if (!(window.MathJax && window.MathJax.Hub)) {
  window.MathJax = {
    tex2jax: {
      inlineMath: [["\\(", "\\)"]],
      displayMath: [["\\[", "\\]"]],
      processEscapes: true,
      processEnvironments: true,
    },
    messageStyle: "none",
  };
}
