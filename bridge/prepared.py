"""Prepared bodies in memory, per prepared key: the solver's ``PreparedBody`` of an object.

A prepared body makes its factorisations (the Poisson reconstruction, the pose transfer) once
and keeps them, so every preview update, interpolated frame, solve and simulation of the same
preparation reuses them.
"""
import collections

from . import bodies, staleness
from .scene import InputError

_BODIES = collections.OrderedDict()   # (prepared key, reduced key, E, rho) -> PreparedBody
_LIMIT = 8


def for_object(obj):
    """The object's ``PreparedBody``, or None if it is not prepared for this mesh (or is stale:
    see staleness.stale_reason)."""
    if staleness.stale_reason(obj, cached=True):
        return None
    settings = obj.rs_elastic
    # Young's modulus and density are not in the prepared key (the modes are cached at 1 Pa
    # and 1 kg/m^3 and moved to them).
    key = (settings.prepared_key, settings.reduced_key, settings.youngs_modulus,
           settings.density)
    if key in _BODIES:
        _BODIES.move_to_end(key)
        return _BODIES[key]
    body = bodies.load_prepared(obj)
    if body is None or body.embedding.shape[0] != len(obj.data.vertices):
        return None
    _BODIES[key] = body
    while len(_BODIES) > _LIMIT:
        _BODIES.popitem(last=False)
    return body


def require(obj):
    """The object's ``PreparedBody`` with its reduced deformer; InputError saying what changed
    since Prepare Body, or that it is not prepared."""
    staleness.require_current(obj)
    body = for_object(obj)
    if body is not None and body.deformer is not None:
        return body
    if obj.rs_elastic.is_prepared:      # prepared, not stale, yet its stages were not rebuilt
        raise InputError(f"'{obj.name}' must be prepared again: its preparation could not be "
                         "rebuilt (the system console says why): run Prepare Body")
    raise InputError(f"'{obj.name}' is not prepared for its current mesh: run Prepare Body")
