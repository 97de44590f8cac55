// MathJax 3 for every page of the site, the notebook pages included: this file configures
// MathJax and then loads it from the site itself (assets/mathjax/, copied by docs/hooks.py from
// the django-static-mathjax package), so nothing comes from a CDN. The Markdown pages carry
// their maths as \( \) and \[ \] (pymdownx.arithmatex), the notebooks as $ $ and $$ $$.
// A notebook page includes this file twice (its own header, then the site's scripts): the
// second time it does nothing.
(function () {
  if (window.__siteMathJax) return;
  window.__siteMathJax = true;
  window.MathJax = {
    tex: {
      inlineMath: [["\\(", "\\)"], ["$", "$"]],
      displayMath: [["\\[", "\\]"], ["$$", "$$"]],
      processEscapes: true,
      processEnvironments: true,
    },
  };
  var script = document.createElement("script");
  script.src = new URL("../assets/mathjax/tex-mml-chtml.js", document.currentScript.src).href;
  script.async = true;
  document.head.appendChild(script);
})();
