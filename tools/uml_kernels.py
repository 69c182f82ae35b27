"""Where tools/vcan-run's user-mode-linux kernels come from, and which of them boot here.

A UML kernel runs as an ordinary process that traces its guest's processes with ptrace, so
whether it boots depends on the host's CPU and kernel, not only on the kernel itself:
Debian bookworm's 6.1 and trixie's 6.12 boot on AMD EPYC hosts but panic on Intel hosts with
AVX-512/AMX under host kernel 6.18 (``userspace - ptrace set fp regs failed, errno = 14``:
the host's extended FPU state is larger than the buffer those kernels hand to
PTRACE_SETREGSET), while newer ones boot on both. So no kernel is trusted before a boot has
proven it on this host, and the verdict is kept per kernel binary and host
(``Verdicts``).

The kernels, in the order they are tried (``candidates``):

1. the installed one: ``ROCOMA_VCAN_UML``, else ``linux.uml`` (Debian's ``user-mode-linux``);
2. kernels fetched earlier into the cache, newest first;
3. kernels fetched now from the newer suites (stable, testing, unstable) of the Debian archive
   this system's apt already uses (its sources and its apt configuration: proxies, keys),
   newest first, never older than the installed package. A fetched kernel is unpacked with
   the C library of its own suite (sid's needs glibc >= 2.38, newer than bookworm's) under
   the cache directory, and started through that library's loader; no system file is
   touched. Only what the guest needs is kept: ``linux.uml``, its CAN modules and the C
   library (about 20 MB a kernel).

The cache is ``ROCOMA_VCAN_CACHE`` (default ``$XDG_CACHE_HOME/rocoma-can/vcan-run``, i.e.
``~/.cache/rocoma-can/vcan-run``): ``kernels/`` (one directory a fetched kernel) and
``verdicts/`` (one small JSON file a kernel binary and host). ``ROCOMA_VCAN_FETCH=0`` fetches
nothing (kernels fetched before are still tried). Deleting the directory is always safe.
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import os
import re
import shutil
import struct
import subprocess
import tarfile
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

#: Where Debian's user-mode-linux package puts the modules of kernel release R: R/kernel/...
SYSTEM_MODULES = Path("/usr/lib/uml/modules")
#: The newer suites a fallback kernel may come from, by their rolling names.
SUITES = ("stable", "testing", "unstable")
#: What the guest loads from a kernel's modules (tools/vcan-run's CAN_MODULES live here).
MODULE_DIRS = ("net/can/", "drivers/net/can/")
#: A fetched kernel's directory: the binary, its C library and its modules.
KERNEL_FILE, LIB_DIR, MODULES_DIR, SOURCE_FILE = "linux.uml", "lib", "modules", "source.json"
#: Bounds on every outside program this module runs.
APT_TIMEOUT = 600.0
VERSION_TIMEOUT = 20.0
LOCK_TIMEOUT = 900.0


class NoKernel(Exception):
    """A kernel cannot be found or fetched; the message says what and why, in one line."""


@dataclass(frozen=True)
class Kernel:
    """A user-mode-linux kernel and how to start it.

    A fetched kernel's binary names its loader by a path relative to its own directory
    (``lib/ld-linux-...``: the absolute one would not fit the ELF header's slot), so it is
    started from that directory (``cwd``), with its C library first (``env``)."""

    path: Path
    modules: Path
    label: str
    version: str = ""  # the package's version, when it came from one
    env: dict[str, str] = field(default_factory=dict)
    cwd: Path | None = None

    def release(self) -> str:
        """The kernel's release (``linux.uml --version``), or "" when it does not say."""
        try:
            out = subprocess.run([str(self.path), "--version"], capture_output=True, text=True,
                                 timeout=VERSION_TIMEOUT, cwd=self.cwd, stdin=subprocess.DEVNULL,
                                 env=dict(os.environ, **self.env))
        except (OSError, subprocess.TimeoutExpired):
            return ""
        words = out.stdout.split()
        return words[0] if out.returncode == 0 and words else ""

    def describe(self) -> str:
        release = self.release()
        return f"{self.label} (kernel {release})" if release else self.label


# ------------------------------------------------------------------------------- the verdicts

@dataclass(frozen=True)
class Verdict:
    """What one boot of a kernel on this host showed: it boots, or it died, with the guest's
    last console lines (what the kernel said before it stopped)."""

    boots: bool
    console: list[str]
    checked: str  # when, as an ISO date and time (UTC)


def host_identity() -> str:
    """The host as a UML kernel sees it: its kernel (release and build) and CPU model; a
    verdict holds for exactly this."""
    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    uname = os.uname()
    return f"{uname.release} {uname.version} {uname.machine} {model}"


class Verdicts:
    """Boot verdicts, one JSON file per (kernel binary, host), written whole or not at all."""

    def __init__(self, cache: Path):
        self.directory = cache / "verdicts"

    def _file(self, kernel: Kernel) -> Path:
        digest = hashlib.sha256()
        with open(kernel.path, "rb") as binary:
            while chunk := binary.read(1 << 20):
                digest.update(chunk)
        digest.update(host_identity().encode())
        return self.directory / f"{digest.hexdigest()[:32]}.json"

    def get(self, kernel: Kernel) -> Verdict | None:
        try:
            data = json.loads(self._file(kernel).read_text())
            return Verdict(bool(data["boots"]), [str(s) for s in data["console"]],
                           str(data["checked"]))
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def put(self, kernel: Kernel, verdict: Verdict) -> None:
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            path = self._file(kernel)
            fd, tmp = tempfile.mkstemp(dir=self.directory, suffix=".tmp")
            with os.fdopen(fd, "w") as out:
                json.dump({"boots": verdict.boots, "console": verdict.console,
                           "checked": verdict.checked, "kernel": str(kernel.path),
                           "host": host_identity()}, out)
            os.replace(tmp, path)
        except OSError:
            pass  # no cache: the kernel is proven again next time


def now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


# --------------------------------------------------------------------------- the candidates

def default_cache() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "rocoma-can" / "vcan-run"


def cache_dir() -> Path:
    return Path(os.environ.get("ROCOMA_VCAN_CACHE") or default_cache())


def installed_kernel(find: Callable[[str], str | None]) -> Kernel:
    """ROCOMA_VCAN_UML or Debian's linux.uml; NoKernel when there is none."""
    wanted = os.environ.get("ROCOMA_VCAN_UML", "linux.uml")
    path = find(wanted)
    if not path:
        raise NoKernel(f"{wanted} not found" if "ROCOMA_VCAN_UML" in os.environ
                       else "user-mode-linux is not installed")
    return Kernel(Path(path), SYSTEM_MODULES, path, version=package_version(Path(path)))


def package_version(path: Path) -> str:
    """The version of the Debian package that installed ``path``, or ""."""
    try:
        owner = subprocess.run(["dpkg-query", "-S", str(path.resolve())], capture_output=True,
                               text=True, timeout=VERSION_TIMEOUT)
        if owner.returncode != 0:
            return ""
        package = owner.stdout.split(":", 1)[0].strip()
        version = subprocess.run(["dpkg-query", "-W", "-f", "${Version}", package],
                                 capture_output=True, text=True, timeout=VERSION_TIMEOUT)
    except (OSError, subprocess.TimeoutExpired):
        return ""
    return version.stdout.strip() if version.returncode == 0 else ""


def fetched_kernels(cache: Path) -> list[Kernel]:
    """The kernels fetched earlier, newest first."""
    kernels = []
    for source in (cache / "kernels").glob(f"*/{SOURCE_FILE}"):
        try:
            info = json.loads(source.read_text())
            kernels.append(fetched_kernel(source.parent, str(info["suite"]),
                                          str(info["version"])))
        except (OSError, ValueError, KeyError, TypeError):
            continue
    return sorted_newest_first(kernels)


def fetched_kernel(directory: Path, suite: str, version: str) -> Kernel:
    return Kernel(directory / KERNEL_FILE, directory / MODULES_DIR,
                  f"Debian {suite}'s user-mode-linux {version} ({directory})", version=version,
                  env={"LD_LIBRARY_PATH": str(directory / LIB_DIR)}, cwd=directory)


def newer(a: str, b: str) -> bool:
    """Debian version ``a`` is newer than ``b`` (dpkg's own comparison)."""
    try:
        return subprocess.run(["dpkg", "--compare-versions", a, "gt", b],
                              timeout=VERSION_TIMEOUT).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return a > b


def sorted_newest_first(kernels: list[Kernel]) -> list[Kernel]:
    ordered: list[Kernel] = []
    for kernel in kernels:
        at = next((i for i, k in enumerate(ordered) if newer(kernel.version, k.version)),
                  len(ordered))
        ordered.insert(at, kernel)
    return ordered


def candidates(installed: Kernel | None, say: Callable[[str], None]) -> Iterator[Kernel]:
    """The kernels to try, in order; fetching happens only when the iteration gets there."""
    if installed is not None:
        yield installed
    cache = cache_dir()
    tried = set()
    for kernel in fetched_kernels(cache):
        tried.add(kernel.version)
        yield kernel
    if os.environ.get("ROCOMA_VCAN_FETCH", "1") == "0":
        return
    floor = installed.version if installed is not None else ""
    yield from DebianFetch(cache, say).kernels(skip=tried, newer_than=floor)


# ------------------------------------------------------------------------ fetching from Debian

class DebianFetch:
    """Newer suites' user-mode-linux from the Debian archive this system's apt uses, through
    apt itself with private state (lists, downloads) in a scratch directory of the cache, so
    nothing of the system's apt state changes. One fetch at a time per cache (a lock)."""

    def __init__(self, cache: Path, say: Callable[[str], None]):
        self.kernels_dir = cache / "kernels"
        self.say = say

    def kernels(self, skip: set[str], newer_than: str) -> Iterator[Kernel]:
        for tool in ("apt-get", "apt-cache", "dpkg-deb"):
            if not shutil.which(tool):
                raise NoKernel(f"cannot fetch a newer kernel: {tool} not found "
                               f"(Debian's apt is how one is fetched)")
        try:
            self.kernels_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise NoKernel(f"cannot fetch a newer kernel: cannot create {self.kernels_dir} "
                           f"({exc.strerror}; set ROCOMA_VCAN_CACHE)") from None
        with self._locked():
            for stale in (*self.kernels_dir.glob(".fetch-*"), *self.kernels_dir.glob(".unpack-*")):
                shutil.rmtree(stale, ignore_errors=True)  # (left by a fetch that was killed)
            yield from self._fetch(skip, newer_than)

    def _fetch(self, skip: set[str], newer_than: str) -> Iterator[Kernel]:
        with tempfile.TemporaryDirectory(prefix=".fetch-", dir=self.kernels_dir) as scratch:
            for kernel in fetched_kernels(self.kernels_dir.parent):  # (one fetched meanwhile)
                if kernel.version not in skip:
                    skip.add(kernel.version)
                    yield kernel
            apt = PrivateApt(Path(scratch), archive_uri())
            self.say(f"fetching the package lists of Debian's {', '.join(SUITES)} "
                     f"from {apt.uri} (the system's apt sources)")
            apt.update()
            for suite, version in apt.versions("user-mode-linux"):
                if version in skip or (newer_than and not newer(version, newer_than)):
                    continue
                skip.add(version)
                self.say(f"fetching Debian {suite}'s user-mode-linux {version} and its "
                         f"C library into {self.kernels_dir}")
                yield self._unpack(apt, suite, version, Path(scratch))

    def _locked(self) -> _Lock:
        return _Lock(self.kernels_dir / ".lock", LOCK_TIMEOUT)

    def _unpack(self, apt: PrivateApt, suite: str, version: str, scratch: Path) -> Kernel:
        debs = scratch / "debs"
        shutil.rmtree(debs, ignore_errors=True)
        debs.mkdir()
        apt.download(debs, f"user-mode-linux={version}", f"libc6/{suite}")
        final = self.kernels_dir / re.sub(r"[^A-Za-z0-9.+~-]", "_", version)
        building = Path(tempfile.mkdtemp(prefix=".unpack-", dir=self.kernels_dir))
        try:
            for deb in sorted(debs.glob("*.deb")):
                unpack(deb, building)
            loader = patch_loader(building / KERNEL_FILE, building / LIB_DIR)
            (building / SOURCE_FILE).write_text(json.dumps(
                {"suite": suite, "version": version, "archive": apt.uri, "loader": loader,
                 "fetched": now()}))
            shutil.rmtree(final, ignore_errors=True)
            os.replace(building, final)
        finally:
            shutil.rmtree(building, ignore_errors=True)
        return fetched_kernel(final, suite, version)


class _Lock:
    """An exclusive flock on a file, waited for at most ``timeout`` seconds."""

    def __init__(self, path: Path, timeout: float):
        self.path, self.timeout = path, timeout
        self.fd = -1

    def __enter__(self) -> _Lock:
        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        deadline = time.monotonic() + self.timeout
        while True:
            try:
                fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return self
            except BlockingIOError:
                if time.monotonic() > deadline:
                    os.close(self.fd)
                    raise NoKernel(f"another tools/vcan-run has been fetching a kernel into "
                                   f"{self.path.parent} for {self.timeout:g} s") from None
                time.sleep(0.2)

    def __exit__(self, *exc: object) -> None:
        os.close(self.fd)  # (releases the lock)


def archive_uri() -> str:
    """The Debian archive of this system's apt sources (not its security archive)."""
    try:
        out = subprocess.run(["apt-get", "indextargets"], capture_output=True, text=True,
                             timeout=APT_TIMEOUT)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise NoKernel(f"cannot read the system's apt sources: {exc}") from None
    for record in out.stdout.split("\n\n"):
        fields = dict(line.split(": ", 1) for line in record.splitlines() if ": " in line)
        if fields.get("Origin") == "Debian" and fields.get("Label") == "Debian" \
                and fields.get("Target-Of") == "deb" and fields.get("Repo-URI"):
            return fields["Repo-URI"]
    raise NoKernel("cannot fetch a newer kernel: the system's apt sources name no Debian "
                   "archive")


class PrivateApt:
    """apt-get and apt-cache with the system's configuration (apt.conf: proxies; its trusted
    keys) but their own sources (``uri`` at SUITES), lists, package status and downloads, all
    under ``root``."""

    def __init__(self, root: Path, uri: str):
        self.uri = uri
        for sub in ("lists/partial", "archives/partial", "parts"):
            (root / sub).mkdir(parents=True)
        (root / "status").write_text("")
        sources = root / "sources.list"
        sources.write_text("".join(f"deb {uri} {suite} main\n" for suite in SUITES))
        self.options = [
            f"-oDir::Etc::SourceList={sources}", f"-oDir::Etc::SourceParts={root / 'parts'}",
            f"-oDir::Etc::Preferences={root / 'none'}",
            f"-oDir::Etc::PreferencesParts={root / 'parts'}",
            f"-oDir::State::Lists={root / 'lists'}", f"-oDir::State::status={root / 'status'}",
            f"-oDir::Cache={root}", "-oDir::Cache::pkgcache=", "-oDir::Cache::srcpkgcache=",
            "-oDebug::NoLocking=1", "-oAcquire::Languages=none", "-oAPT::Get::List-Cleanup=0",
            "-oquiet=1"]
        if os.geteuid() == 0:  # downloads go where the unprivileged _apt user cannot write
            self.options.append("-oAPT::Sandbox::User=root")

    def _run(self, *argv: str, cwd: Path | None = None) -> str:
        try:
            out = subprocess.run([argv[0], *self.options, *argv[1:]], capture_output=True,
                                 text=True, timeout=APT_TIMEOUT, cwd=cwd,
                                 stdin=subprocess.DEVNULL,
                                 env=dict(os.environ, DEBIAN_FRONTEND="noninteractive"))
        except subprocess.TimeoutExpired:
            raise NoKernel(f"{' '.join(argv)} took over {APT_TIMEOUT:g} s") from None
        except OSError as exc:
            raise NoKernel(f"cannot run {argv[0]}: {exc}") from None
        if out.returncode != 0:
            said = [line for line in out.stderr.splitlines() if line.startswith(("E:", "W:"))]
            raise NoKernel(f"{' '.join(argv)} failed: {' '.join(said[-2:]) or out.returncode}")
        return out.stdout

    def update(self) -> None:
        self._run("apt-get", "update")

    def versions(self, package: str) -> list[tuple[str, str]]:
        """(suite codename, version) of ``package`` in the suites, newest version first,
        each version once."""
        seen: list[tuple[str, str]] = []
        for line in self._run("apt-cache", "madison", package).splitlines():
            parts = [p.strip() for p in line.split("|")]
            if len(parts) == 3 and parts[0] == package:
                suite = parts[2].split()[1].split("/")[0] if len(parts[2].split()) > 1 else ""
                if suite and all(v != parts[1] for _, v in seen):
                    seen.append((suite, parts[1]))
        return seen

    def download(self, into: Path, *packages: str) -> None:
        self._run("apt-get", "download", *packages, cwd=into)


# ------------------------------------------------------------------------------ unpacking

def unpack(deb: Path, into: Path) -> None:
    """From a .deb, only what the guest needs: linux.uml, the CAN modules (modules/R/kernel/
    net/can, drivers/net/can), the C library's shared objects (lib/, flat)."""
    with subprocess.Popen(["dpkg-deb", "--fsys-tarfile", str(deb)], stdout=subprocess.PIPE,
                          stdin=subprocess.DEVNULL) as dpkg:
        assert dpkg.stdout is not None
        try:
            with tarfile.open(fileobj=dpkg.stdout, mode="r|") as tar:
                for member in tar:
                    target = wanted(member.name)
                    if target is None or not (member.isfile() or member.issym()):
                        continue
                    dest = into / target
                    dest.parent.mkdir(parents=True, exist_ok=True)
                    if member.issym():
                        if "/" not in member.linkname:  # (a library's other name)
                            os.symlink(member.linkname, dest)
                        continue
                    source = tar.extractfile(member)
                    assert source is not None
                    with open(dest, "wb") as out:
                        shutil.copyfileobj(source, out)
                    dest.chmod(0o755 if member.mode & 0o111 else 0o644)
        except tarfile.TarError as exc:
            raise NoKernel(f"cannot unpack {deb.name}: {exc}") from None
        finally:
            dpkg.stdout.close()
            dpkg.wait(APT_TIMEOUT)
    if dpkg.returncode != 0:
        raise NoKernel(f"dpkg-deb could not read {deb.name} (exit status {dpkg.returncode})")


def wanted(name: str) -> str | None:
    """Where a package member goes in a kernel's directory, or None to leave it out."""
    name = name.removeprefix("./")
    if name == "usr/bin/linux.uml":
        return KERNEL_FILE
    module = re.fullmatch(r"usr/lib/uml/modules/([^/]+)/kernel/(.+)", name)
    if module and module.group(2).startswith(MODULE_DIRS):
        return f"{MODULES_DIR}/{module.group(1)}/kernel/{module.group(2)}"
    library = re.fullmatch(r"(?:usr/)?lib/[^/]*-linux-[^/]*/([^/]+\.so(?:\.\d+)*)", name)
    if library:
        return f"{LIB_DIR}/{library.group(1)}"
    return None


PT_INTERP = 3


def patch_loader(binary: Path, libs: Path) -> str:
    """Point an x86-64 ELF binary's program interpreter at the loader in ``libs``, by a path
    relative to the binary's directory (written into the header's own slot: the absolute
    path would not fit). Returns the path written."""
    data = bytearray(binary.read_bytes())
    if data[:4] != b"\x7fELF" or data[4] != 2 or data[5] != 1:
        raise NoKernel(f"{binary} is not a 64-bit little-endian ELF file")
    phoff, = struct.unpack_from("<Q", data, 0x20)
    phentsize, phnum = struct.unpack_from("<HH", data, 0x36)
    for i in range(phnum):
        kind, _, offset, _, _, size = struct.unpack_from("<IIQQQQ", data, phoff + i * phentsize)
        if kind != PT_INTERP:
            continue
        loader = Path(data[offset:offset + size].rstrip(b"\0").decode()).name
        if not (libs / loader).is_file():
            raise NoKernel(f"the C library fetched for {binary} has no {loader}")
        relative = f"{libs.name}/{loader}".encode()
        if len(relative) >= size:
            raise NoKernel(f"{binary}: no room for the loader path {relative.decode()}")
        data[offset:offset + size] = relative.ljust(size, b"\0")
        binary.write_bytes(bytes(data))
        return relative.decode()
    raise NoKernel(f"{binary} names no program interpreter")
