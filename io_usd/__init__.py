"""USD caches, scene I/O and pyrender previews for Warp CFX."""

from .cache import ROLES, CacheReader, CacheWriter, read_cache
from .validate import validation_errors, validation_report

__all__ = ["ROLES", "CacheReader", "CacheWriter", "read_cache", "validation_errors", "validation_report"]
