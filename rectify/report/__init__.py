"""Reports: the one builder (``builder``: residual CSVs, figures, ``report.json``, the HTML page) and every
image-side figure (``figures``). See ``docs/report.md``.
"""
