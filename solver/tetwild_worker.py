"""Standalone fTetWild worker, run by ``solver.tetmesh`` in a separate process.

Usage: python tetwild_worker.py IN.npz OUT.npz

IN.npz holds ``vertices`` (n, 3) float64, ``faces`` (m, 3) int32, scalars ``edge_length_fac``,
``epsilon``, ``num_threads`` (0 = all cores), ``time_limit`` (seconds, 0 = none) and, optionally,
``stop_energy`` and ``max_iterations`` (fTetWild's optimisation stops at that AMIPS energy or
after that many passes; pytetwild's defaults when absent). OUT.npz
receives ``nodes`` (N, 3) float64 and ``tets`` (E, 4) int32. A crash of fTetWild kills only this
process. Imports nothing but numpy, pytetwild and the standard library (no package-relative
imports: it is run as a script).

fTetWild shuffles the order in which it inserts the input triangles with a generator seeded by
``std::random_device``, so two runs on the same surface give different meshes. On Linux the worker
makes that seed a constant (``seed_random_device``), so Prepare is reproducible: same surface and
settings, same tets. Elsewhere, or when the library's layout is not the one expected, it meshes
unseeded and says so in OUT.npz (``seeded``).

The parent kills this process at the time limit. It also bounds itself, a few seconds later, with
an alarm whose default action ends the process even inside fTetWild's native code: so a worker
whose parent died (Blender was killed) does not mesh on for minutes. POSIX only.
"""

import ctypes
import math
import os
import signal
import struct
import sys

import numpy as np

# (name in IN.npz, pytetwild keyword, type) of the optional optimisation settings
OPTIMISATION = (("stop_energy", "stop_energy", float), ("max_iterations", "num_opt_iter", int))
SELF_LIMIT_MARGIN = 5   # [s] after the parent's limit, so the parent's kill and message come first


def bound_own_time(time_limit):
    """Let SIGALRM (default action: terminate) end this process after the limit and a margin."""
    if time_limit > 0.0 and hasattr(signal, "alarm"):
        signal.signal(signal.SIGALRM, signal.SIG_DFL)
        signal.alarm(int(math.ceil(time_limit)) + SELF_LIMIT_MARGIN)


# unsigned int std::random_device::_M_getval(), what each draw of a std::random_device calls
RANDOM_DEVICE_GETVAL = b"_ZNSt13random_device9_M_getvalEv"
FIXED_SEED = 20231   # any constant: fTetWild only needs the same shuffle every run


def _plt_slot_offset(library_path, symbol):
    """Offset from the library's load base of the .got.plt slot through which it calls
    ``symbol`` (its R_X86_64_JUMP_SLOT relocation), or None (no such call, or no x86-64 ELF)."""
    with open(library_path, "rb") as f:
        elf = f.read()
    if elf[:6] != b"\x7fELF\x02\x01" or struct.unpack_from("<H", elf, 0x12)[0] != 0x3E:
        return None                                     # 64-bit little-endian x86-64 only
    shoff, = struct.unpack_from("<Q", elf, 0x28)
    shentsize, shnum = struct.unpack_from("<HH", elf, 0x3A)
    # (name, type, flags, addr, offset, size, link, info, addralign, entsize) per section
    sections = [struct.unpack_from("<IIQQQQIIQQ", elf, shoff + i * shentsize) for i in range(shnum)]
    for _, kind, _, _, offset, size, link, _, _, entsize in sections:
        if kind != 4:                                   # SHT_RELA
            continue
        symtab, strtab = sections[link], sections[sections[link][6]]
        for at in range(offset, offset + size, entsize):
            r_offset, r_info = struct.unpack_from("<QQ", elf, at)
            if r_info & 0xFFFFFFFF != 7:                 # R_X86_64_JUMP_SLOT
                continue
            name_at = strtab[4] + struct.unpack_from("<I", elf, symtab[4] + (r_info >> 32) * 24)[0]
            if elf[name_at:elf.index(b"\0", name_at)] == symbol:
                return r_offset
    return None


def _mappings(library_path):
    """[(start, end, permissions, file offset)] of the library's mappings in this process."""
    with open("/proc/self/maps") as maps:
        rows = [line.split() for line in maps]
    return [(*(int(x, 16) for x in row[0].split("-")), row[1], int(row[2], 16))
            for row in rows if len(row) >= 6 and row[5] == library_path]


# A Python callback: it takes the GIL, which the calling thread already holds (pytetwild does not
# release it, and fTetWild draws its seed once, on that thread, before its parallel parts).
@ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_void_p)
def _fixed_random_device(_device):
    return FIXED_SEED


def seed_random_device(library_path):
    """Point the loaded library's calls of std::random_device::_M_getval at a constant; True when
    done. Only where the slot is found, writable and holds libstdc++'s own function (so nothing
    but that call changes)."""
    try:
        slot_offset = _plt_slot_offset(library_path, RANDOM_DEVICE_GETVAL)
        mappings = _mappings(library_path)
        # a shared library's addresses count from where its file offset 0 is mapped
        bases = [start for start, _, _, file_offset in mappings if file_offset == 0]
        if slot_offset is None or not bases:
            return False
        slot = bases[0] + slot_offset
        if not any(start <= slot < end and rights.startswith("rw")
                   for start, end, rights, _ in mappings):
            return False
        libstdcxx = ctypes.CDLL("libstdc++.so.6")
        original = ctypes.cast(getattr(libstdcxx, RANDOM_DEVICE_GETVAL.decode()), ctypes.c_void_p)
        pointer = ctypes.c_void_p.from_address(slot)
        if pointer.value != original.value:
            return False
        pointer.value = ctypes.cast(_fixed_random_device, ctypes.c_void_p).value
        return True
    except (OSError, ValueError, AttributeError, struct.error):
        return False


def main(in_path, out_path):
    with np.load(in_path, allow_pickle=False) as data:
        vertices = np.ascontiguousarray(data["vertices"], dtype=np.float64)
        faces = np.ascontiguousarray(data["faces"], dtype=np.int32)
        edge_length_fac = float(data["edge_length_fac"])
        epsilon = float(data["epsilon"])
        num_threads = int(data["num_threads"]) if "num_threads" in data.files else 0
        time_limit = float(data["time_limit"]) if "time_limit" in data.files else 0.0
        optimisation = {key: cast(data[name]) for name, key, cast in OPTIMISATION
                        if name in data.files}
    bound_own_time(time_limit)
    if hasattr(os, "RTLD_NOW"):         # bind every call slot when the library loads
        sys.setdlopenflags(os.RTLD_NOW)
    import pytetwild
    from pytetwild import PyfTetWildWrapper

    seeded = (sys.platform.startswith("linux")
              and seed_random_device(os.path.realpath(PyfTetWildWrapper.__file__)))
    nodes, tets = pytetwild.tetrahedralize(vertices, faces, edge_length_fac=edge_length_fac,
                                           epsilon=epsilon, num_threads=num_threads, quiet=True,
                                           **optimisation)
    with open(out_path, "wb") as f:
        np.savez(f, nodes=np.asarray(nodes, dtype=np.float64),
                 tets=np.asarray(tets, dtype=np.int32), seeded=seeded)


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: tetwild_worker.py IN.npz OUT.npz")
    main(sys.argv[1], sys.argv[2])
