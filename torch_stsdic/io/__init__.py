"""Files in and out: image series (:mod:`.images`), frame specifications (:mod:`.specs`),
users' small tables (:mod:`.tables`),
HDF5 result files (:mod:`.results`) and exports for other tools (:mod:`.export`)."""

from .export import export_csv
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
    "add_fields",
    "export_csv",
    "load_series",
    "natural_sort_key",
    "parse_frame_spec",
    "read_mask",
    "read_points",
    "read_results",
    "read_table",
    "read_timestamps",
]
