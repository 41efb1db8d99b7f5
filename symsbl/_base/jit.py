"""Compiling CasADi Functions to C: one C loop per (mapped) Function, with a fallback, kept for later runs.

:func:`jit_wrap` wraps a Function (usually a ``map`` or ``mapaccum``) in one MX Function, generates its
C source with CasADi's code generator, compiles it with the system C compiler into a shared library
and loads it back with ``casadi.external``. Without a compiler, or when compiling fails, the
Function runs on CasADi's virtual machine instead (``jit="auto"``) or an error says why
(``jit=True``). Generated code that cannot run here whatever the compiler (it calls a function the C
library lacks, such as ``erfinv``, or holds a Function CasADi cannot export to C) also runs on the
virtual machine, after one warning per reason: a library is opened with every symbol bound at once
(``RTLD_NOW``) before CasADi calls into it, since a symbol bound lazily that is missing ends the process
at its first call.

Compiling costs 0.1-2 s a Function (gcc ``-O3``; a source over :data:`LARGE_SOURCE` is compiled at ``-O1``,
whose time grows less steeply: a five-mass chain's identification from an empty cache took 70 s of CPU at
``-O3``, 51 s so, and 30 s against 38 s once compiled), often more than the computation it speeds up on
a short record, and the same structures come back run after run (the same library, the same
identified model re-simulated, the same refinement step). Compiled libraries are therefore kept:

- in memory for the process, by the Function's serialised graph (:func:`jit_lookup`);
- on disk between processes, by a hash of the generated C source together with the compiler,
  its flags, the CPU and the CasADi version (so a library is never loaded on a machine or with a
  compiler it was not built for). The directory is ``$SYMSBL_JIT_CACHE`` if set, else
  ``$XDG_CACHE_HOME/symsbl/jit`` (``~/.cache/symsbl/jit``); it is created private to the user
  (mode 0700) and ignored if another user owns it or others may write to it. A library is
  written under a temporary name and renamed into place, so concurrent processes never load a
  partial file. The least recently used libraries beyond :data:`DISK_FILES` are removed.
  ``SYMSBL_JIT_CACHE=off`` (or ``0``, or empty) keeps compiled code for the process only.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import functools
import glob
import hashlib
import io
import itertools
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from collections import OrderedDict

import casadi as ca

from .errors import SymsblError, expected

__all__ = [
    "compiler",
    "jit_wrap",
    "jit_lookup",
    "cache_dir",
    "DISK_FILES",
    "CACHE_ENV",
    "MAX_AUTO_SOURCE",
    "LARGE_SOURCE",
]

#: Environment variable naming the directory of compiled libraries kept between runs ("off": none).
CACHE_ENV = "SYMSBL_JIT_CACHE"
#: Compiled libraries kept on disk; the least recently used beyond this are removed (typically 20-200 kB each).
DISK_FILES = 256
#: Temporary files older than this (seconds) are left over from an interrupted compilation.
_STALE = 3600.0

_FLAGS = ("-O3", "-march=native", "-w")  # -w: generated code (empty copies) warns harmlessly
#: Largest generated C source compiled under ``jit="auto"`` (bytes): gcc's time grows faster than the source
#: (measured: 80 kB in 1 s, 200 kB in 1.2 s, 730 kB in 15.5 s), so a larger function runs on the virtual
#: machine, whose time is proportional to its size.
MAX_AUTO_SOURCE = 256_000
#: Generated C longer than this (bytes: what only a fit's passes compile) is compiled at ``-O1``, whose time
#: grows less steeply than ``-O3``'s; the code runs slower (see the module's description).
LARGE_SOURCE = MAX_AUTO_SOURCE
_LARGE_FLAGS = ("-O1", "-march=native", "-w")
_MEMORY: OrderedDict[tuple, ca.Function] = OrderedDict()
_MEMORY_SIZE = 64
_SEEN: dict = {}  # keys asked for without compiling (jit="auto" on short data), and the work asked so far
_UNUSABLE: set = set()  # keys whose generated code cannot run here: not generated again in the process
_WARNED: set[str] = set()  # reasons already warned about: one warning each per process
_SCRATCH: str | None = None
_COUNTER = itertools.count()
_OFF = frozenset({"", "0", "off", "no", "false", "none"})


def compiler() -> str | None:
    """The C compiler used to compile Functions (gcc or cc on PATH), or None."""
    return shutil.which("gcc") or shutil.which("cc")


def cache_dir() -> str | None:
    """The directory of compiled libraries kept between runs, or None (disabled or not usable).

    See the module's description for how it is chosen and when it is not used.
    """
    setting = os.environ.get(CACHE_ENV)
    if setting is not None and setting.strip().lower() in _OFF:
        return None
    if setting:
        path = os.path.expanduser(setting)
    else:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        path = os.path.join(base, "symsbl", "jit")
    try:
        os.makedirs(path, mode=0o700, exist_ok=True)
        st = os.stat(path)
    except OSError:
        return None
    foreign = hasattr(os, "getuid") and st.st_uid != os.getuid()
    if foreign or st.st_mode & 0o022 or not os.access(path, os.W_OK | os.X_OK):
        return None  # another user could place a library here that this process would load
    return path


def _scratch_dir() -> str:
    """A private temporary directory for the process, removed at exit (used when no cache directory is)."""
    global _SCRATCH
    if _SCRATCH is None:
        _SCRATCH = tempfile.mkdtemp(prefix="symsbl_jit_")
        atexit.register(shutil.rmtree, _SCRATCH, True)
    return _SCRATCH


@functools.lru_cache(maxsize=4)
def _fingerprint(cc: str) -> str:
    """What a compiled library depends on besides its source: compiler, flags, CPU, CasADi."""
    try:
        version = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        version = ""
    cpu = ""
    try:
        with open("/proc/cpuinfo") as f:  # -march=native: the instruction set of this CPU
            lines = [line for line in f if line.startswith(("model name", "flags"))]
        cpu = "".join(sorted(set(lines)))
    except OSError:
        cpu = platform.processor()
    casadi_version = ca.__version__  # type: ignore[attr-defined]  # absent from CasADi's stubs
    return "\n".join([cc, version, " ".join(_FLAGS), platform.machine(), cpu, casadi_version])


def jit_lookup(key) -> ca.Function | None:
    """A compiled function cached in memory under ``key`` by :func:`jit_wrap`, or None."""
    if key in _MEMORY:
        _MEMORY.move_to_end(key)
        return _MEMORY[key]
    return None


def jit_wrap(
    fn: ca.Function,
    name: str,
    jit,
    error: type[SymsblError],
    *,
    only_cached: bool = False,
    key=None,
    max_source: int = MAX_AUTO_SOURCE,
    work: int = 0,
    worth: int = 0,
) -> tuple[ca.Function, bool]:
    """``fn`` compiled as one C function (an MX wrapper compiled with gcc), or ``fn`` itself.

    Compiling a wrapper around a ``map`` or ``mapaccum`` produces one C loop, which removes
    CasADi's per-call overhead of the virtual machine (0.1-1 us a sample). Compiled functions are
    kept in memory per process and on disk between runs (see the module's description).

    Parameters
    ----------
    fn : ca.Function
    name : str
    jit : {"auto", True, False}
        ``"auto"`` compiles when a compiler exists and falls back silently (with one warning when the
        generated code cannot run: see the module's description); ``True`` requires it.
    error : SymsblError subclass
        Raised when ``jit=True`` cannot be honoured.
    only_cached : bool
        Compile only if the same function was asked for before in this process or was compiled in
        an earlier run (compiling would not pay off for one short use, and does for a structure
        used again: fits over many records, seeds or windows).
    key : hashable, optional
        The in-memory cache key (default: a hash of ``fn``'s serialised graph and ``name``); a
        caller that knows a cheaper one (the small step the function was built from) passes it.
    max_source : int
        Largest C source compiled under ``jit="auto"`` (bytes; default :data:`MAX_AUTO_SOURCE`): a caller
        that will call the function many times (a fit's passes) may allow more.
    work, worth : int
        With ``only_cached`` and ``worth`` > 0: compile once the work of every request for this function (this
        one's ``work`` included, in the caller's units) reaches ``worth``, rather than from the second request
        (a held-out record simulated twice does not repay a compilation that costs a hundred such runs).

    Returns
    -------
    (ca.Function, bool)
        The function to call and whether it is compiled.
    """
    if jit is False:
        return fn, False
    cc = compiler()
    if cc is None:
        if jit is True:
            raise error(
                expected(
                    "jit",
                    "a C compiler (gcc or cc on PATH) for jit=True",
                    "none found",
                    "install gcc or pass jit='auto'",
                    raw=True,
                )
            )
        return fn, False
    key = (hashlib.sha1(fn.serialize().encode()).hexdigest(), name) if key is None else key
    cached = jit_lookup(key)
    if cached is not None:
        return cached, True
    if key in _UNUSABLE and jit == "auto":
        return fn, False
    args = [ca.MX.sym(fn.name_in(i), fn.sparsity_in(i)) for i in range(fn.n_in())]
    wrapper = ca.Function(name, args, fn.call(args), fn.name_in(), fn.name_out())
    done = _SEEN.get(key, 0)
    # compiled from the second request on (a structure used again), or once the work asked for repays it
    build = not only_cached or (done + work >= worth if worth > 0 else key in _SEEN)
    try:
        compiled = _compile(wrapper, cc, build, max_source if jit == "auto" else None)
    except (RuntimeError, OSError, subprocess.CalledProcessError) as err:
        if jit is True:
            text = err.stderr.decode(errors="replace") if isinstance(err, subprocess.CalledProcessError) else str(err)
            reason = (text.strip().splitlines() or [str(err)])[-1][:200]
            raise error(
                expected("jit", "a successful compilation for jit=True", reason, "pass jit='auto'", raw=True)
            ) from None
        return fn, False
    if isinstance(compiled, str):
        return _unusable(fn, key, compiled, jit, error)
    if compiled is None:
        _SEEN[key] = done + work
        return fn, False
    _MEMORY[key] = compiled
    if len(_MEMORY) > _MEMORY_SIZE:
        _MEMORY.popitem(last=False)
    return compiled, True


def _unusable(fn: ca.Function, key, reason: str, jit, error: type[SymsblError]) -> tuple[ca.Function, bool]:
    """``fn`` uncompiled, after one warning per ``reason`` (``jit="auto"``); an error for ``jit=True``."""
    if jit is True:
        raise error(expected("jit", "generated C code that runs for jit=True", reason, "pass jit='auto'", raw=True))
    _UNUSABLE.add(key)
    if reason not in _WARNED:
        _WARNED.add(reason)
        warnings.warn(
            f"compiled code: {reason}; such functions run on CasADi's virtual machine instead (the same values, "
            "slower)",
            RuntimeWarning,
            stacklevel=3,
        )
    return fn, False


def _source(fn: ca.Function) -> tuple[str, str]:
    """The C source of ``fn`` and ``""``, or ``""`` and why CasADi cannot export it."""
    generator = ca.CodeGenerator("symsbl_jit.c", {"with_header": False})
    notices = io.StringIO()
    try:
        with contextlib.redirect_stderr(notices):  # CasADi's notice of a part it cannot export: ours says it once
            generator.add(fn)
            source = generator.dump()
    except RuntimeError as err:
        last = (str(err).strip().splitlines() or [""])[-1].split(": ")[-1][:160]
        return "", f"CasADi's code generator cannot export a function ({last})"
    unsupported = re.search(r"#error Code generation not supported for (\w+)", source)
    if unsupported:
        return "", f"CasADi cannot generate C code for {unsupported.group(1)}"
    sys.stderr.write(notices.getvalue())
    return source, ""


def _lacks(library: str) -> str:
    """Why ``library`` cannot run, if it calls a symbol nothing provides; else ``""`` (it binds, or is damaged)."""
    try:
        ctypes.CDLL(library, mode=getattr(os, "RTLD_NOW", 0))  # every symbol bound now: a missing one is an OSError
    except OSError as err:
        missing = str(err).partition("undefined symbol: ")[2].strip()
        return f"the C library lacks {missing!r}, which the generated C code calls" if missing else ""
    return ""


def _compile(fn: ca.Function, cc: str, build: bool = True, limit: int | None = None) -> ca.Function | str | None:
    """``fn`` as a compiled shared library: loaded from the disk cache, or (if ``build``) compiled.

    Returns None when ``build`` is false, or its C source is longer than ``limit``, and no compiled
    library exists; a string, why, when the generated code cannot run here whatever the compiler (a
    library kept on disk that calls a missing symbol stays there, so a later run is told without
    compiling it again). The compiler runs as a
    Python subprocess, so Ctrl-C during a compilation interrupts the program (a compiler started
    through ``system()``, as CasADi's own JIT does, ignores SIGINT in the caller while it runs).
    """
    source, unusable = _source(fn)
    if unusable:
        return unusable
    flags = _LARGE_FLAGS if len(source) > LARGE_SOURCE else _FLAGS
    marked = _fingerprint(cc) + ("" if flags == _FLAGS else "\n" + " ".join(flags))  # the flags it is built with
    digest = hashlib.sha256((marked + "\n" + source).encode()).hexdigest()[:40]
    kept = cache_dir()
    directory = kept or _scratch_dir()
    library = os.path.join(directory, digest + ".so")
    if os.path.exists(library):
        _touch(library)
        unusable = _lacks(library)
        if unusable:
            return unusable
        with contextlib.suppress(RuntimeError):  # unreadable: built again below
            return ca.external(fn.name(), library)
    if not build or (limit is not None and len(source) > limit):
        return None
    partial = os.path.join(directory, f".{digest}.{os.getpid()}.{next(_COUNTER)}")
    try:
        with open(partial + ".c", "w") as f:
            f.write(source)
        subprocess.run(
            [cc, *flags, "-shared", "-fPIC", partial + ".c", "-o", partial + ".so"], check=True, capture_output=True
        )
        os.replace(partial + ".so", library)
    finally:
        for leftover in (partial + ".c", partial + ".so"):
            if os.path.exists(leftover):
                os.remove(leftover)
    if kept:
        _prune(kept)
    return _lacks(library) or ca.external(fn.name(), library)


def _touch(path: str) -> None:
    """Mark a cached library as used now (the pruning removes the least recently used)."""
    try:
        os.utime(path)
    except OSError:
        pass


def _prune(directory: str) -> None:
    """Remove the least recently used libraries beyond :data:`DISK_FILES` and stale temporary files."""
    now = time.time()
    try:
        for stale in glob.glob(os.path.join(directory, ".*.*")):
            if now - os.path.getmtime(stale) > _STALE:
                os.remove(stale)
        libraries = sorted(glob.glob(os.path.join(directory, "*.so")), key=os.path.getmtime)
        for old in libraries[: max(len(libraries) - DISK_FILES, 0)]:
            os.remove(old)
    except OSError:  # another process removed it first
        pass
