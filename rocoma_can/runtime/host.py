"""Is this host fit to run a control loop at 1 kHz: the kernel, the scheduler rights, the
CPU clock and isolation (``rocoma-can doctor``). Everything here reads; nothing is
changed, and the one probe that must try (SCHED_FIFO) tries on a thread of its own that
ends at once, so the calling process never runs real-time.

Each finding is a ``Check``: FAIL blocks the configuration (the loop could not run as
configured), WARN costs latency or robustness, N/A could not be judged here (and says why).
"""
from __future__ import annotations

import glob
import os
import pwd
import resource
import threading
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

Status = Literal["ok", "warn", "fail", "n/a"]

CPU_SYSFS = Path("/sys/devices/system/cpu")
#: how long the SCHED_FIFO probe thread may take to report (it makes one system call)
PROBE_TIMEOUT = 5.0
#: CapEff bits (linux/capability.h)
CAP_IPC_LOCK = 14
CAP_SYS_NICE = 23
_RT_KERNEL = ("Debian: sudo apt-get install linux-image-rt-amd64 (arm64: -rt-arm64); Ubuntu: "
              "sudo pro enable realtime-kernel; then reboot into it")
_RTPRIO_FIX = ("allow this user: a line '{user} - rtprio 99' in "
               "/etc/security/limits.d/rocoma.conf (then log in again), or run as root; for "
               "a systemd service LimitRTPRIO=99; for a container --cap-add SYS_NICE "
               "--ulimit rtprio=99")
_ROOT_RT_FIX = ("give the process CAP_SYS_NICE (a container: --cap-add SYS_NICE); root is "
                "refused too where its cgroup has no real-time budget (cpu.rt_runtime_us 0)")


@dataclass(frozen=True)
class Check:
    """One line of the checklist: ``fix`` is the command or step that clears a miss."""
    name: str
    status: Status
    found: str
    fix: str = ""

    def as_dict(self) -> dict[str, str]:
        return asdict(self)


def blocking(checks: Iterable[Check]) -> bool:
    return any(c.status == "fail" for c in checks)


def _read(path: Path | str) -> str | None:
    try:
        return Path(path).read_text().strip()
    except OSError:
        return None


def kernel_check(version: str | None = None, realtime_flag: str | None = None) -> Check:
    """PREEMPT_RT: without it a cycle can wait milliseconds behind the kernel (softirqs,
    locks held with preemption off), whatever the loop's priority."""
    version = os.uname().version if version is None else version
    if realtime_flag is None:
        realtime_flag = _read("/sys/kernel/realtime") or ""
    if "PREEMPT_RT" in version or realtime_flag == "1":
        return Check("kernel: PREEMPT_RT", "ok", f"real-time kernel ({version})")
    hint = (" (PREEMPT_DYNAMIC: booting with preempt=full helps some, PREEMPT_RT more)"
            if "PREEMPT_DYNAMIC" in version else "")
    return Check("kernel: PREEMPT_RT", "warn",
                 f"not a real-time kernel: {os.uname().release} {version}{hint}", _RT_KERNEL)


def _capability(bit: int) -> bool:
    """The calling process holds the capability (CapEff in /proc/self/status)."""
    for line in (_read("/proc/self/status") or "").splitlines():
        if line.startswith("CapEff:"):
            return bool(int(line.split()[1], 16) >> bit & 1)
    return False


def _limit(value: int, unit: str = "") -> str:
    if value == resource.RLIM_INFINITY:
        return "unlimited"
    return f"{value // 1024} KiB" if unit == "bytes" else str(value)


def try_sched_fifo(priority: int) -> str | None:
    """Why SCHED_FIFO ``priority`` is refused to this process, None when it is granted.
    Tried for real (rights, rtprio limits and a cgroup's real-time budget all decide) on a
    short-lived thread: the policy is the thread's and ends with it."""
    outcome: list[str | None] = []

    def probe() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            outcome.append(None)
        except OSError as exc:
            outcome.append(exc.strerror or str(exc))

    thread = threading.Thread(target=probe, name="doctor-sched-probe", daemon=True)
    thread.start()
    thread.join(PROBE_TIMEOUT)
    return outcome[0] if outcome else f"the probe thread did not answer in {PROBE_TIMEOUT} s"


def priority_check(configured: int | None, have_config: bool) -> Check:
    """May the loop run SCHED_FIFO at the configured priority (at 1 without one)."""
    name = "scheduler: SCHED_FIFO"
    tried = configured or 1
    soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
    rights = (f"uid {os.getuid()}, CAP_SYS_NICE {'yes' if _capability(CAP_SYS_NICE) else 'no'}, "
              f"RLIMIT_RTPRIO {_limit(soft)}")
    refused = try_sched_fifo(tried)
    if refused is not None:
        status: Status = "fail" if configured else "warn"
        because = f"realtime.priority {configured} is" if configured else "priority 1 is"
        fix = _ROOT_RT_FIX if os.getuid() == 0 else \
            _RTPRIO_FIX.format(user=pwd.getpwuid(os.getuid()).pw_name)
        return Check(name, status, f"{because} refused ({refused}; {rights})", fix)
    if have_config and not configured:
        return Check(name, "warn", f"permitted ({rights}), but the config sets no "
                     "realtime.priority: the loop runs at normal priority",
                     "realtime: {priority: 80} in the config")
    return Check(name, "ok", f"priority {tried} permitted ({rights}; tried on a thread "
                 "that ended at once)")


def _rss_bytes() -> int | None:
    for line in (_read("/proc/self/status") or "").splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    return None


def memlock_check() -> Check:
    """mlockall: a page fault in a cycle (a page swapped or not yet touched) costs up to
    milliseconds. Read from the limit and CAP_IPC_LOCK; the manager does not lock memory
    itself today, so a miss only matters for a deployment that does."""
    name = "memory: mlockall"
    soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    rss = _rss_bytes()
    if soft == resource.RLIM_INFINITY or _capability(CAP_IPC_LOCK):
        return Check(name, "ok", f"permitted (RLIMIT_MEMLOCK {_limit(soft, 'bytes')}, "
                     "CAP_IPC_LOCK "
                     f"{'yes' if _capability(CAP_IPC_LOCK) else 'no'})")
    need = f"; this process alone uses {rss // 2**20} MiB" if rss else ""
    return Check(name, "warn", f"RLIMIT_MEMLOCK is {_limit(soft, 'bytes')}{need}: mlockall of a "
                 "running manager would be refused",
                 "a line '<user> - memlock unlimited' in /etc/security/limits.d/rocoma.conf "
                 "(log in again), or LimitMEMLOCK=infinity for a systemd service")


def governor_check(cpus: Sequence[int] | None = None, root: Path = CPU_SYSFS) -> Check:
    """cpufreq governor: any other than 'performance' lowers the clock while the loop
    sleeps between cycles, and the next cycle runs at the low clock until it rises."""
    name = "CPU frequency governor"
    found: dict[int, str] = {}
    for path in glob.glob(str(root / "cpu[0-9]*" / "cpufreq" / "scaling_governor")):
        cpu = int(Path(path).parent.parent.name[3:])
        value = _read(path)
        if value is not None and (cpus is None or cpu in cpus):
            found[cpu] = value
    if not found:
        where = f" for CPUs {list(cpus)}" if cpus else ""
        return Check(name, "n/a", f"no cpufreq in this kernel{where} ({root}/cpu*/cpufreq "
                     "absent: a virtual machine, or the firmware fixes the clock)")
    slow = {cpu: g for cpu, g in sorted(found.items()) if g != "performance"}
    if not slow:
        return Check(name, "ok", f"performance on CPUs {sorted(found)}")
    listed = ", ".join(f"cpu{c} {g}" for c, g in slow.items())
    return Check(name, "warn", listed,
                 "sudo cpupower frequency-set -g performance (or echo performance | sudo tee "
                 "/sys/devices/system/cpu/cpu*/cpufreq/scaling_governor)")


def parse_cpu_list(text: str) -> set[int]:
    """A kernel CPU list ("1-3,6") as numbers."""
    cpus: set[int] = set()
    for part in text.replace("\n", ",").split(","):
        part = part.strip()
        if not part:
            continue
        low, _, high = part.partition("-")
        cpus.update(range(int(low), int(high or low) + 1))
    return cpus


def isolation_check(configured: set[int] | None, root: Path = CPU_SYSFS) -> Check:
    """Isolated CPUs (isolcpus=): the scheduler puts nothing else there, so the loop pinned
    to one (realtime.cpus) is not preempted by other work."""
    name = "CPU isolation"
    text = _read(root / "isolated")
    if text is None:
        return Check(name, "n/a", f"{root}/isolated is absent (an old kernel)")
    isolated = parse_cpu_list(text)
    boot = "add isolcpus={0} nohz_full={0} rcu_nocbs={0} to GRUB_CMDLINE_LINUX in " \
           "/etc/default/grub, sudo update-grub, reboot"
    if configured:
        allowed = os.sched_getaffinity(0)
        missing = sorted(configured - allowed)
        if missing:
            return Check(name, "warn", f"realtime.cpus {sorted(configured)}: CPUs {missing} "
                         f"are not available to this process (it may use {sorted(allowed)}); "
                         "the loop would run unpinned", "realtime.cpus: CPUs this host has")
        outside = sorted(configured - isolated)
        if outside:
            return Check(name, "warn", f"realtime.cpus {sorted(configured)}: {outside} not "
                         f"isolated (isolated: {sorted(isolated) or 'none'})",
                         boot.format(",".join(map(str, sorted(configured)))))
        return Check(name, "ok", f"realtime.cpus {sorted(configured)} isolated")
    if isolated:
        return Check(name, "warn", f"CPUs {sorted(isolated)} are isolated but the loop is "
                     "pinned to none of them", f"realtime: {{cpus: [{min(isolated)}]}} in the "
                     "config")
    return Check(name, "n/a", "no CPU isolated and none configured (optional: it keeps "
                 "other work off the loop's CPU)",
                 boot.format(max(os.sched_getaffinity(0))) + ", then realtime.cpus")


def realtime_checks(priority: int | None, cpus: set[int] | None,
                    have_config: bool) -> list[Check]:
    return [kernel_check(), priority_check(priority, have_config), memlock_check(),
            governor_check(sorted(cpus) if cpus else None), isolation_check(cpus)]
