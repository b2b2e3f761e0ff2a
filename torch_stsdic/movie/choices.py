"""The run's device choices live in :mod:`torch_stsdic.core.choices` (the FFT searches of
``core`` take one of them too); this name is that very module, so that a choice set here
(``choices.MASKED_GROUPS = True``) is the one the package reads."""

import sys

from torch_stsdic.core import choices as _choices

sys.modules[__name__] = _choices
