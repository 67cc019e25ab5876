#!/bin/sh
# Run a command inside the GUI test root (tools/ui/build_root.sh) with /proc, /dev and a fresh
# /dev/shm mounted, all in a private mount and PID namespace: the mounts exist only there (the
# host never sees them) and go when the command ends. If the caller dies first, however it dies,
# the namespace dies with it (setpriv --pdeathsig, then unshare --kill-child), so no process or
# mount is left behind.
#   tools/ui/in_root.sh ROOT COMMAND [ARGS...]       (as root; the environment is cleared)
if [ -z "${RS_IN_ROOT_NAMESPACE:-}" ]; then
  RS_IN_ROOT_NAMESPACE=1 exec setpriv --pdeathsig KILL \
    unshare --mount --propagation private --pid --fork --kill-child /bin/sh "$0" "$@"
fi
root=$1
shift
mount -t proc proc "$root/proc" && mount --rbind /dev "$root/dev" \
  && mount -t tmpfs -o mode=1777 shm "$root/dev/shm" || exit 1
# Not exec: this shell is the namespace's first process, and all others end with it.
chroot "$root" /usr/bin/env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin LANG=C.UTF-8 HOME=/root "$@"
