"""Files of the stereo side: one module per file family, one section of ``docs/formats.md`` each.
"""
