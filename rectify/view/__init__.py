"""The browser view of a step's results (``rectify view``, ``stereo view``; docs/view.md).

``folder`` finds what an output folder holds and resolves the paths the page asks for (nothing outside
the folder); ``data`` reads the step's measurements from its files into the JSON the page draws; ``server``
answers the page's requests on 127.0.0.1; ``export`` writes the same answers as a static folder. The page
itself (HTML, JavaScript, CSS; no library) is in ``static/``.
"""
