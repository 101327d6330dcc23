"""Fields: the callable (value and gradient, chunked) that every extractor consumes."""

from .analytic import DiscUDF, PlaneUDF, SphereUDF, TorusUDF
from .base import DEFAULT_CHUNK, Field, normalize

__all__ = ["Field", "normalize", "DEFAULT_CHUNK", "PlaneUDF", "SphereUDF", "DiscUDF", "TorusUDF"]
