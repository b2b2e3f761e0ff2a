"""Files in and out: image series (:mod:`.images`; one image file's header and pixels in
:mod:`.imagefile`), frame specifications (:mod:`.specs`),
users' small tables (:mod:`.tables`),
HDF5 result files (:mod:`.results`). Camera movies (Photron MRAW,
Phantom CINE, video files) are image series too (:mod:`.movies`). Exports for other
tools (CSV, MATLAB, VTK, with strains) sit a layer up, in
:mod:`torch_stsdic.analysis.export`."""

from torch_stsdic.io.images import IMAGE_EXTENSIONS, ImageSeries, load_series
from torch_stsdic.io.results import (
    CSV_COLUMNS,
    DEFAULT_FIELDS,
    RESULTS_FORMAT,
    RESULTS_FORMAT_VERSION,
    STRAIN_FIELDS,
    ResultFileError,
    Results,
    ResultWriter,
    add_fields,
    read_results,
)
from torch_stsdic.io.specs import InputError, natural_sort_key, parse_frame_spec
from torch_stsdic.io.tables import read_mask, read_points, read_table, read_timestamps
from torch_stsdic.io.units import Units, units_of

__all__ = [
    "CSV_COLUMNS",
    "DEFAULT_FIELDS",
    "IMAGE_EXTENSIONS",
    "RESULTS_FORMAT",
    "RESULTS_FORMAT_VERSION",
    "STRAIN_FIELDS",
    "ImageSeries",
    "InputError",
    "ResultFileError",
    "ResultWriter",
    "Results",
    "Units",
    "add_fields",
    "load_series",
    "natural_sort_key",
    "parse_frame_spec",
    "read_mask",
    "read_points",
    "read_results",
    "read_table",
    "read_timestamps",
    "units_of",
]
