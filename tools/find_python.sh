#!/usr/bin/env bash
# Print the path of a working CPython interpreter of version X.Y (e.g. 3.13), or nothing.
# Looks at pythonX.Y on PATH (a pyenv shim only counts if it really runs), then at pyenv's own
# installs, so it works whichever pyenv version is active.
set -u
want="$1"
check() { [ -x "$1" ] && [ "$("$1" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null)" = "$want" ]; }
if candidate=$(command -v "python$want" 2>/dev/null) && check "$candidate"; then
  echo "$candidate"; exit 0
fi
root=$(pyenv root 2>/dev/null || echo "${PYENV_ROOT:-$HOME/.pyenv}")
for candidate in $(ls -d "$root"/versions/"$want".*/bin/"python$want" 2>/dev/null | sort -V -r); do
  if check "$candidate"; then echo "$candidate"; exit 0; fi
done
exit 0
