"""``stsdic view``: a result in the browser, or the region of a run drawn on its images.

:mod:`.source` reads a result file lazily (one row or one point per request), :mod:`.region`
turns a drawn box and polygons into ``--roi`` and a ``--mask`` image, :mod:`.server` serves
the page (``assets/``: plain HTML, CSS and JavaScript shipped with the package) and the data
on 127.0.0.1 with the standard library's HTTP server.
"""
