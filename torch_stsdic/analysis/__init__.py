"""What is made of solved points: POI grids and neighbours, strains, the trust checks' tests,
the run's result object, smoothing in time, and exports for other tools (CSV, MATLAB, VTK).

Layer 3: imports from :mod:`torch_stsdic.kernels`, :mod:`torch_stsdic.core` and
:mod:`torch_stsdic.io`."""
