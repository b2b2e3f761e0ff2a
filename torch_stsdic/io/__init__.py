"""Files in and out: image series (:mod:`.images`; one image file's header and pixels in
:mod:`.imagefile`), frame specifications (:mod:`.specs`),
users' small tables (:mod:`.tables`),
HDF5 result files (:mod:`.results`) and exports for other tools (:mod:`.export`)."""

from .export import FORMATS, export_csv, export_mat, export_results, export_vtk
from .images import IMAGE_EXTENSIONS, ImageSeries, load_series
from .results import (
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
from .specs import InputError, natural_sort_key, parse_frame_spec
from .tables import read_mask, read_points, read_table, read_timestamps
from .units import Units, units_of

__all__ = [
    "CSV_COLUMNS",
    "DEFAULT_FIELDS",
    "FORMATS",
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
    "export_csv",
    "export_mat",
    "export_results",
    "export_vtk",
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
