"""Files of the image side: one module per file family, one section of ``docs/formats.md`` each.

A format imports the formulas whose objects it builds, never the reverse. ``common`` holds the
``format``/``version`` stamp and its check, and the CSV toolkit the other formats (and ``stereo.formats``) use.
"""
