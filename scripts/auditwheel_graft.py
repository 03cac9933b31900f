"""auditwheel (the pinned one of scripts/wheel.sh's tool venv) that also grafts into the wheel the
libraries its manylinux policies let a wheel take from the system but a headless machine lacks.

The policies allow, beside glibc and the GCC runtime, libX11, libXext, libXrender, libICE, libSM,
libGL, GLib, expat and zlib; Debian's libcairo2 needs libX11, libXext and libXrender (its Xlib
surfaces, which the renderer never uses), and a server or a container without a desktop has
none of them: the wheel's mll_server would not start there. So only glibc, the GCC runtime,
expat and zlib stay external (ALWAYS_THERE); whatever else the binaries need goes into
multi_lunar_lander.libs/. A wheel may bring more than its policy requires: the tag stays the
oldest policy the binaries satisfy, and plain `auditwheel show` reports the same.
scripts/wheel-test.sh runs the result on a Debian without those libraries.

Usage: python scripts/auditwheel_graft.py repair [auditwheel repair's arguments]
"""

from __future__ import annotations

import sys

from auditwheel import policy
from auditwheel.main import main

# glibc's libraries and the GCC runtime, which the policies' symbol versions constrain; and
# expat (fontconfig's) and zlib, which the python3 of Debian and Ubuntu links itself (pyexpat,
# zlib), so any machine that runs the package with it has them. Debian 12's expat needs glibc
# 2.36: grafted, it would raise the tag from manylinux_2_35 and leave out Ubuntu 22.04.
ALWAYS_THERE = frozenset(
    {
        "libexpat.so.1",
        "libz.so.1",
        "libc.so.6",
        "libm.so.6",
        "libmvec.so.1",
        "libanl.so.1",
        "libdl.so.2",
        "librt.so.1",
        "libnsl.so.1",
        "libutil.so.1",
        "libpthread.so.0",
        "libresolv.so.2",
        "libgcc_s.so.1",
        "libstdc++.so.6",
        "libatomic.so.1",
    }
)

_whitelist = policy._fixup_musl_libc_soname  # Where WheelPolicies reads each policy's whitelist.


def _always_there_only(libc, arch, whitelist):
    return _whitelist(libc, arch, [soname for soname in whitelist if soname in ALWAYS_THERE])


if __name__ == "__main__":
    policy._fixup_musl_libc_soname = _always_there_only
    sys.exit(main())
