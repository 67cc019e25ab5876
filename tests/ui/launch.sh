#!/bin/sh
# Runs inside the GUI test root: Xvfb on a free display, then Blender on it; Xvfb ends with Blender.
#   launch.sh RUN_FOLDER BLENDER_ARGS...
# RUN_FOLDER/display gets the display number once Xvfb listens; RUN_FOLDER/blender.exit Blender's
# exit status. The caller holds this script's standard input open and never writes to it: when
# the caller ends, however it ends (even killed), the input closes and Blender and Xvfb are killed.
run=$1
shift
exec 4<&0          # the caller's pipe, kept for the watcher below
Xvfb -displayfd 3 -screen 0 1920x1080x24 +extension GLX -nolisten tcp \
  3>"$run/display" </dev/null >"$run/xvfb.log" 2>&1 &
xvfb=$!
waited=0
until grep -q . "$run/display" 2>/dev/null; do
  if ! kill -0 "$xvfb" 2>/dev/null || [ "$waited" -ge 300 ]; then
    echo "launch: Xvfb did not start (see xvfb.log)" >&2
    kill "$xvfb" 2>/dev/null
    exit 3
  fi
  sleep 0.1
  waited=$((waited + 1))
done
export DISPLAY=":$(cat "$run/display")"
blender "$@" </dev/null &
blender=$!
(cat <&4 >/dev/null; kill -KILL "$blender" "$xvfb" 2>/dev/null) &
watcher=$!
wait "$blender"
status=$?
echo "$status" > "$run/blender.exit"
kill "$xvfb" "$watcher" 2>/dev/null
wait "$xvfb"
exit "$status"
