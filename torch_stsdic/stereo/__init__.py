"""Stereo STS-DIC: 3D shape, displacement and velocity from two cameras (``docs/stereo.md``).

Modules: :mod:`.calibration` (the camera system in one convention and its readers),
:mod:`.triangulation` (projection, distortion removal, triangulation, uncertainty),
:mod:`.matching` (left -> right reference match), :mod:`.run` (:func:`track_stereo`),
:mod:`.result` (:class:`StereoResult`), :mod:`.render` (synthetic stereo movies with exact
truth), :mod:`.cli` (the ``stsdic stereo`` command module).
"""

from .calibration import Camera, StereoCalibration, load_calibration
from .matching import CrossMatch, match_stereo
from .result import StereoResult, best_fit_plane
from .run import track_stereo
from .triangulation import project, triangulate, undistort

__all__ = ["Camera", "StereoCalibration", "load_calibration", "CrossMatch", "match_stereo",
           "StereoResult", "best_fit_plane", "track_stereo", "project", "triangulate",
           "undistort"]
