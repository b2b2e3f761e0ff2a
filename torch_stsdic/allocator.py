"""Process memory (:mod:`torch_stsdic.kernels.allocator`, where it lives so that every layer
may call it): ``keep_freed_memory`` for a program's start, ``release_freed_memory`` between
a run's passes."""

from torch_stsdic.kernels.allocator import keep_freed_memory, release_freed_memory

__all__ = ["keep_freed_memory", "release_freed_memory"]
