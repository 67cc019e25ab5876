"""Writing a result as one transaction: never destroy before the new result exists.

An operator computes its whole result first; then, inside ``transaction``, it writes the new
data, each write saying how to take itself back (``undo``), and queues the removal of the old
(``remove``), which runs only once every write has succeeded. Files that the old result used are
deleted last (``after``). So:
- an exception in a write takes back every write so far, in reverse order, and leaves as one
  line (InputError: "<what> failed (<why>); nothing was changed");
- removals that can be taken back (a modifier, made again from its settings) run first; a
  removal that fails while everything removed so far can be taken back does the same as a
  write; once something old is gone for good (shape keys: they run last) the new result stays
  in place, and the line says so;
- an action queued with ``after`` (deleting a file nothing uses any more) that fails is only
  printed: the data that used the file is gone already.

Transactions nest: a write opened inside another's transaction joins it, so an operator's own
records and the bake it writes commit together. Main thread only.

What may write at all: ``require_object_mode``. Outside Object Mode a mesh's shape keys and
vertices live in the mode's own copy (Edit Mode's BMesh), and leaving the mode writes that copy
back over whatever was written meanwhile.
"""
import contextlib
import os

from .scene import InputError

_OPEN = []     # the transaction being written, if any (nested ones join it)


def reason(exc):
    """One line saying why `exc` happened."""
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.strerror}: {exc.filename}" if exc.filename else exc.strerror
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


class Writes:
    """The undo log and the queued removals of one transaction (see the module's text)."""

    def __init__(self, what):
        self.what = what
        self._undo = []
        self._removals = []
        self._after = []

    def undo(self, function):
        """`function()` takes back a write that was just done (or is about to be)."""
        self._undo.append(function)

    def remove(self, function, undo=None):
        """`function()` removes old data once every write has succeeded; `undo()`, if there is
        one, puts it back (such removals run first)."""
        self._removals.append((undo is None, len(self._removals), function, undo))

    def after(self, function):
        """`function()` runs last (deleting a file nothing uses any more); failures are printed."""
        self._after.append(function)

    def roll_back(self):
        for function in reversed(self._undo):
            if function is None:
                continue
            try:
                function()
            except Exception as exc:    # keep taking back the others
                print(f"RS Elastic: {self.what}: could not take back a write ({reason(exc)})")
        self._undo.clear()

    def fail(self, exc):
        """Take back every write and raise the one line for `exc`."""
        self.roll_back()
        if isinstance(exc, InputError):
            raise exc
        raise InputError(f"{self.what} failed ({reason(exc)}); nothing was changed") from exc

    def commit(self):
        for _, _, function, undo in sorted(self._removals, key=lambda r: r[:2]):
            try:
                function()
            except Exception as exc:
                if None not in self._undo:
                    self.fail(exc)
                raise InputError(f"{self.what}: the new result is in place, but part of the old "
                                 f"one could not be removed ({reason(exc)})") from exc
            self._undo.append(undo)      # None: gone for good
        for function in self._after:
            try:
                function()
            except Exception as exc:
                print(f"RS Elastic: {self.what}: {reason(exc)}")


@contextlib.contextmanager
def transaction(what):
    """Writes of one result (see the module's text); joins the transaction already open."""
    if _OPEN:
        yield _OPEN[-1]
        return
    writes = Writes(what)
    _OPEN.append(writes)
    try:
        yield writes
    except Exception as exc:
        _OPEN.pop()
        writes.fail(exc)
    except BaseException:          # Ctrl+C and exits: take back, but let them through
        _OPEN.pop()
        writes.roll_back()
        raise
    else:
        _OPEN.pop()
        writes.commit()


def keep_values(writes, struct, names):
    """Note the values of the properties `names` of an RNA struct: undone, they come back."""
    saved = {name: getattr(struct, name) for name in names}

    def undo():
        for name, value in saved.items():
            setattr(struct, name, value)
    writes.undo(undo)


def keep_id_properties(writes, owner, names):
    """Note the ID properties `names` of `owner` (present or not): undone, they come back."""
    saved = {}
    for name in names:
        value = owner.get(name)
        if hasattr(value, "to_dict"):
            value = value.to_dict()
        elif hasattr(value, "to_list"):
            value = value.to_list()
        saved[name] = value

    def undo():
        for name, value in saved.items():
            if value is None:
                if owner.get(name) is not None:
                    del owner[name]
            else:
                owner[name] = value
    writes.undo(undo)


def remove_file_quietly(path):
    """Delete `path` if it is there (taking back a file this transaction wrote)."""
    with contextlib.suppress(FileNotFoundError):
        os.remove(path)


def mode_name(obj):
    """'Edit Mode', 'Sculpt Mode', 'Weight Paint mode', … for the object's current mode."""
    name = obj.bl_rna.properties["mode"].enum_items[obj.mode].name
    return name if name.endswith("Mode") else f"{name} mode"


def require_object_mode(obj, verb, allowed=('OBJECT',)):
    """Refuse (InputError) to `verb` while the object is in another mode than `allowed`: leaving
    Edit Mode would overwrite what was written (the keys come back as they were in the mode), and
    the paint and sculpt modes work on the mesh as it was when they were entered."""
    if obj.mode not in allowed:
        tab = " (Tab)" if obj.mode == 'EDIT' else ""
        raise InputError(f"'{obj.name}' is in {mode_name(obj)}: switch to Object Mode{tab} "
                         f"to {verb}")
