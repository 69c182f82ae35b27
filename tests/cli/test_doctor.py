"""rocoma_can/cli/doctor.py, rocoma_can/runtime/can_checks.py, host.py: ``rocoma-can doctor``: the
link checks judged from ``ip -details -statistics -json`` output captured from real kernels
(tests/fixtures/ip_link/, taken in the vcan-run guest: vcan0 up and down, and an slcan controller —
a real CAN device of kind "can" on a pty — stopped, up at 1 Mbit/s, told ERROR-WARNING and BUS-OFF
by its adapter protocol; and two links that are not CAN, eth0 and lo, taken on a development host's
kernel 6.18), and the host checks as they run on this machine. tests/vcan/test_vcan_doctor.py runs
the verb against live links."""
from __future__ import annotations

import json
import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from fixtures.budgets import within
from fixtures.paths import ROOT, TESTS

from rocoma_can.drivers.link.can_link import LinkReading, from_sysfs, parse_ip_link
from rocoma_can.drivers.plan.config import BusConfig
from rocoma_can.runtime.can_checks import RESTART_MS, TXQUEUELEN_MIN, Wanted, link_checks
from rocoma_can.runtime.host import (
    CPU_SYSFS,
    governor_check,
    kernel_check,
    parse_cpu_list,
    try_sched_fifo,
)

CAPTURED = TESTS / "fixtures" / "ip_link"
EXAMPLES = ROOT / "rocoma_can" / "examples"
#: a CLI run: a Python start and a few reads of /sys and /proc
CLI_BUDGET = within(10)


def captured(name: str) -> LinkReading:
    link = parse_ip_link((CAPTURED / f"{name}.json").read_text())
    return LinkReading(link.name, link)


def by_name(checks):
    return {c.name.split(": ", 1)[1]: c for c in checks}


# -- parsing what the kernel said ------------------------------------------------------------

def test_a_vcan_link_is_read_as_virtual_without_a_controller():
    up, down = parse_ip_link((CAPTURED / "vcan0_up.json").read_text()), \
        parse_ip_link((CAPTURED / "vcan0_down.json").read_text())
    assert (up.name, up.kind, up.up, up.mtu, up.txqueuelen) == ("vcan0", "vcan", True, 72, 1000)
    assert (up.state, up.bitrate, up.restart_ms, up.berr) == (None, None, None, None)
    assert not down.up and down.operstate == "DOWN"


def test_a_can_controller_is_read_with_its_bit_rate_state_and_counters():
    link = parse_ip_link((CAPTURED / "slcan_up.json").read_text())
    assert (link.kind, link.up, link.state, link.bitrate, link.restart_ms, link.txqueuelen) \
        == ("can", True, "ERROR-ACTIVE", 1_000_000, 0, 128)
    assert link.counters["bus_off"] == 0 and link.counters["tx_errors"] == 0
    assert not link.fd and link.data_bitrate is None
    off = parse_ip_link((CAPTURED / "slcan_busoff.json").read_text())
    assert (off.state, off.up, off.operstate, off.counters["bus_off"]) == \
        ("BUS-OFF", True, "DOWN", 1)


@pytest.mark.parametrize("text", ["", "not json", "[]", "{}", '[{"ifname": "a"}, {}]'])
def test_output_that_is_not_one_link_is_refused(text):
    with pytest.raises(ValueError):
        parse_ip_link(text)


# -- judging a link against its bus ----------------------------------------------------------

def test_a_healthy_controller_at_the_configured_rate_passes_but_restart_ms_0_warns():
    checks = by_name(link_checks(captured("slcan_up"), Wanted.of(BusConfig("socketcan",
                                                                          "can0", 1_000_000))))
    assert {k: c.status for k, c in checks.items()} == {
        "exists": "ok", "up": "ok", "bit rate": "ok", "CAN FD": "n/a",
        "controller state": "ok", "error counters": "ok", "txqueuelen": "ok",
        "restart-ms": "warn"}
    assert f"restart-ms {RESTART_MS}" in checks["restart-ms"].fix


def test_another_bit_rate_fails_with_the_command_that_sets_the_configured_one():
    check = by_name(link_checks(captured("slcan_up"),
                                Wanted.of(BusConfig("socketcan", "can0", 500_000))))["bit rate"]
    assert check.status == "fail"
    assert "1000000 bit/s, the config says 500000" in check.found
    assert check.fix == ("sudo ip link set can0 down && sudo ip link set can0 type can "
                         f"bitrate 500000 restart-ms {RESTART_MS} && sudo ip link set can0 up")


def test_a_config_without_bitrate_is_compared_with_the_assumed_one_as_a_warning():
    check = by_name(link_checks(captured("slcan_up"),
                                Wanted.of(BusConfig("socketcan", "can0"))))["bit rate"]
    assert check.status == "ok"  # 1 Mbit/s: what check-config assumed
    stopped = parse_ip_link((CAPTURED / "slcan_stopped.json").read_text())
    assert stopped.bitrate == 1_000_000 and stopped.txqueuelen == 1000


def test_bus_off_fails_and_error_warning_warns():
    want = Wanted.of(BusConfig("socketcan", "can0", 1_000_000))
    off = by_name(link_checks(captured("slcan_busoff"), want))
    assert off["controller state"].status == "fail"
    assert "sudo ip link set can0 type can restart" in off["controller state"].fix
    assert off["error counters"].status == "warn" and "bus off 1" in off["error counters"].found
    warning = by_name(link_checks(captured("slcan_warning"), want))
    assert warning["controller state"].status == "warn"
    assert "ERROR-WARNING" in warning["controller state"].found


def test_a_small_transmit_queue_warns_with_the_reason():
    link = parse_ip_link((CAPTURED / "slcan_up.json").read_text().replace('"txqlen":128',
                                                                          '"txqlen":10'))
    check = by_name(link_checks(LinkReading("can0", link), Wanted("can0")))["txqueuelen"]
    assert check.status == "warn" and "ENOBUFS" in check.found
    assert check.fix == f"sudo ip link set can0 txqueuelen {TXQUEUELEN_MIN}"


def test_vcan_has_no_bit_rate_and_a_down_vcan_fails_with_its_fix():
    want = Wanted.of(BusConfig("socketcan", "vcan0", 1_000_000))
    up = by_name(link_checks(captured("vcan0_up"), want))
    assert {k: c.status for k, c in up.items()} == {"exists": "ok", "up": "ok",
                                                    "bit rate": "n/a", "state": "n/a"}
    down = by_name(link_checks(captured("vcan0_down"), want))
    assert down["up"].status == "fail" and down["up"].fix == "sudo ip link set vcan0 up"


def test_can_fd_on_vcan_is_its_mtu():
    fd = Wanted.of(BusConfig("socketcan", "vcan0", 1_000_000, fd=True, data_bitrate=5_000_000))
    assert by_name(link_checks(captured("vcan0_up"), fd))["CAN FD"].status == "ok"
    classic = parse_ip_link((CAPTURED / "vcan0_up.json").read_text().replace('"mtu":72',
                                                                             '"mtu":16'))
    check = by_name(link_checks(LinkReading("vcan0", classic), fd))["CAN FD"]
    assert check.status == "fail" and "mtu 72" in check.fix


def test_fd_configured_on_a_classic_controller_fails():
    fd = Wanted.of(BusConfig("socketcan", "can0", 1_000_000, fd=True, data_bitrate=2_000_000))
    check = by_name(link_checks(captured("slcan_up"), fd))["CAN FD"]
    assert check.status == "fail"
    assert "dbitrate 2000000 fd on" in check.fix


def test_a_missing_link_fails_naming_it_and_how_to_create_it():
    (vcan,) = link_checks(LinkReading("vcan3", None), Wanted("vcan3"))
    assert (vcan.status, vcan.found) == ("fail", "no network interface 'vcan3'")
    assert "sudo ip link add dev vcan3 type vcan" in vcan.fix
    (can,) = link_checks(LinkReading("can7", None), Wanted("can7"))
    assert can.status == "fail" and "correct the channel" in can.fix


def test_without_iproute2_the_details_are_not_judged_and_the_install_is_named():
    basic = parse_ip_link((CAPTURED / "vcan0_up.json").read_text())
    reading = LinkReading("vcan0", basic, "iproute2 (ip) is not installed",
                          "sudo apt-get install iproute2")
    checks = by_name(link_checks(reading, Wanted.of(BusConfig("socketcan", "vcan0",
                                                              1_000_000))))
    detail = checks["bit rate, state, counters"]
    assert detail.status == "warn" and detail.fix == "sudo apt-get install iproute2"


# -- a link that is not CAN -----------------------------------------------------------------

@pytest.mark.parametrize("name, link_type", [("eth0_up", "ether"), ("lo_up", "loopback")])
def test_a_link_that_is_not_can_is_read_as_such(name, link_type):
    """Captured from a real kernel: an Ethernet link and the loopback, both up."""
    link = parse_ip_link((CAPTURED / f"{name}.json").read_text())
    assert link.link_type == link_type and not link.is_can
    assert parse_ip_link((CAPTURED / "vcan0_up.json").read_text()).is_can
    assert parse_ip_link((CAPTURED / "slcan_up.json").read_text()).is_can


@pytest.mark.parametrize("name, channel", [("eth0_up", "eth0"), ("lo_up", "lo")])
@pytest.mark.parametrize("with_config", [True, False])
def test_a_link_that_is_not_can_fails_and_is_not_judged_further(name, channel, with_config):
    """eth0 and lo are up and have no bit rate to compare: judged as a CAN link, nothing
    blocked them. One FAIL saying what the link is, and nothing after it."""
    want = Wanted.of(BusConfig("socketcan", channel, 1_000_000)) if with_config \
        else Wanted(channel)
    (check,) = link_checks(captured(name), want)
    assert (check.name, check.status) == (f"{channel}: exists", "fail")
    assert "not a CAN link" in check.found and "link/" in check.found, check.found
    assert "ip link shows" in check.fix and "link/can" in check.fix


def test_a_link_that_is_not_can_is_known_from_sysfs_alone(tmp_path):
    """Without iproute2, /sys/class/net/DEV/type says it: ARPHRD_CAN (280) or not."""
    for name, kind in (("can0", "280"), ("eth0", "1"), ("lo", "772"), ("odd", "65534")):
        (tmp_path / name).mkdir()
        for key, value in (("flags", "0x1003"), ("mtu", "16"), ("type", kind)):
            (tmp_path / name / key).write_text(value + "\n")
    reading = {n: from_sysfs(n, tmp_path) for n in ("can0", "eth0", "lo", "odd")}
    assert [(n, r.is_can) for n, r in reading.items() if r] == [
        ("can0", True), ("eth0", False), ("lo", False), ("odd", False)]
    assert reading["eth0"].link_type == "ether" and reading["lo"].link_type == "loopback"
    assert reading["odd"].link_type == "type 65534"
    (check,) = link_checks(LinkReading("lo", reading["lo"], "iproute2 (ip) is not "
                                       "installed"), Wanted("lo"))
    assert check.status == "fail" and "not a CAN link" in check.found


def test_doctor_fails_for_the_loopback_as_a_can_channel(tmp_path):
    """Every host has lo: doctor --channel lo, and a config whose bus is lo, both exit 1
    with the FAIL line (it said "nothing blocks it")."""
    done = doctor("--channel", "lo")
    assert done.returncode == 1, done.stdout
    assert "FAIL  lo: exists" in done.stdout and "not a CAN link" in done.stdout
    assert done.stdout.splitlines()[-1].endswith(": blocks it")
    done, checks = doctor_on(tmp_path, "lo")
    assert done.returncode == 1 and checks["lo: exists"]["status"] == "fail"
    assert not [name for name in checks if name.startswith("lo: ") and name != "lo: exists"]


# -- this host, as it is ---------------------------------------------------------------------

def test_the_kernel_check_says_what_it_found():
    check = kernel_check()
    assert os.uname().version in check.found
    rt = "PREEMPT_RT" in os.uname().version or Path("/sys/kernel/realtime").exists()
    assert check.status == ("ok" if rt else "warn")
    assert check.status == "ok" or "linux-image-rt" in check.fix
    assert kernel_check("#1 SMP PREEMPT_RT Thu", "").status == "ok"


def test_without_cpufreq_the_governor_is_not_applicable_and_says_why(tmp_path):
    here = governor_check()
    if not list(CPU_SYSFS.glob("cpu[0-9]*/cpufreq/scaling_governor")):
        assert here.status == "n/a" and "no cpufreq" in here.found
    else:
        assert here.status in ("ok", "warn") and "cpu" in here.found.lower()
    assert governor_check(root=tmp_path).status == "n/a"


def test_the_sched_fifo_probe_leaves_this_thread_as_it_was():
    before = os.sched_getscheduler(0)
    refused = try_sched_fifo(1)
    assert os.sched_getscheduler(0) == before == os.SCHED_OTHER
    assert refused is None or isinstance(refused, str)


def test_cpu_lists_as_the_kernel_writes_them():
    assert parse_cpu_list("1-3,6\n") == {1, 2, 3, 6}
    assert parse_cpu_list("") == set()


# -- the verb --------------------------------------------------------------------------------

def doctor(*args: str, prefix: tuple[str, ...] = ()) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*prefix, sys.executable, "-m", "rocoma_can", "doctor", *args],
                          capture_output=True, text=True, timeout=CLI_BUDGET)


def test_json_is_a_list_of_checks_and_the_exit_code_follows_the_failures():
    done = doctor("--json")
    checks = json.loads(done.stdout)
    assert checks and all(set(c) == {"name", "status", "found", "fix"} for c in checks)
    assert {c["status"] for c in checks} <= {"ok", "warn", "fail", "n/a"}
    names = [c["name"] for c in checks]
    assert {"kernel: PREEMPT_RT", "scheduler: SCHED_FIFO", "memory: mlockall",
            "CPU frequency governor", "CPU isolation", "configuration"} <= set(names)
    assert done.returncode == (1 if any(c["status"] == "fail" for c in checks) else 0)


def test_timing_runs_the_bare_loop_at_the_rate_and_reports_both_footprints():
    # 1000 cycles a check, the fewest it takes: 0.2 s each at 5 kHz
    done = doctor("--timing", "0.4", "--rate", "5000", "--json")
    checks = {c["name"]: c for c in json.loads(done.stdout)}
    cache, memory = checks["timing: work in the cache"], checks["timing: work over 4 MiB"]
    for check in (cache, memory):
        assert check["status"] in ("ok", "warn")
        # 40 % of a 200 µs period, at the asked rate, at normal priority (no config)
        assert check["found"].startswith("5000 Hz, 80 µs of Python work a cycle: ")
        cycles = int(check["found"].split(" overruns in ")[1].split(" cycles")[0])
        assert 1 <= cycles <= 1001
        assert bool(check["fix"]) == (check["status"] == "warn")
    assert memory["found"].endswith("x)")  # its speed's spread
    assert "timing: work in the cache" not in {c["name"] for c in json.loads(
        doctor("--json").stdout)}  # measured only when asked


def test_the_text_output_ends_with_the_verdict():
    done = doctor()
    lines = done.stdout.splitlines()
    assert lines[0].startswith("doctor: ")
    assert lines[-1].endswith("nothing blocks it" if done.returncode == 0 else "blocks it")


@pytest.mark.parametrize("args, says", [
    (("x.yaml", "--channel", "can0"), "not both"),
    (("--interface", "socketcan"), "--interface needs --channel"),
    (("--interface", "pcan", "--channel", "PCAN_USBBUS1"), "SocketCAN links only"),
    (("--timing", "0"), "expected seconds > 0"),
    (("--timing", "121"), "120 s at most"),
    (("--timing", "1"), "needs 1000 cycles, at least 2 s"),
    (("--rate", "500"), "with --timing"),
    (("--rate", "20000", "--timing"), "0 < HZ <= 10000"),
    (("--timing", "1", "--rate", "0"), "expected a number > 0"),
])
def test_usage_errors_exit_2(args, says):
    done = doctor(*args)
    assert done.returncode == 2 and says in done.stderr


def test_a_config_that_does_not_load_gives_its_own_errors_and_exit_2(tmp_path):
    path = tmp_path / "robot.yaml"
    data = yaml.safe_load((EXAMPLES / "bench_vcan.yaml").read_text())
    data["rate"] = -5
    path.write_text(yaml.safe_dump(data))
    done = doctor(str(path))
    assert done.returncode == 2 and done.stdout == ""
    assert f"{path}: rate" in done.stderr
    missing = doctor(str(tmp_path / "none.yaml"))
    assert missing.returncode == 2 and "cannot read" in missing.stderr


def doctor_on(tmp_path: Path, channel: str) -> tuple[subprocess.CompletedProcess[str], dict]:
    """doctor --json of the shipped vcan bench with its bus on ``channel``: the run and its
    checks by name."""
    path = tmp_path / "robot.yaml"
    data = yaml.safe_load((EXAMPLES / "bench_vcan.yaml").read_text())
    data["bus"]["channel"] = channel
    path.write_text(yaml.safe_dump(data))
    done = doctor(str(path), "--json")
    return done, {c["name"]: c for c in json.loads(done.stdout)}


def test_a_config_on_a_missing_link_fails_naming_it(tmp_path):
    done, checks = doctor_on(tmp_path, "vcan9")
    assert done.returncode == 1
    assert checks["vcan9: exists"]["status"] == "fail"
    assert "ip link add dev vcan9 type vcan" in checks["vcan9: exists"]["fix"]


def _without_rt_rights() -> tuple[str, ...] | None:
    """A prefix that runs a command without the right to SCHED_FIFO, None when there is none
    on this machine."""
    if os.getuid() != 0:
        soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
        return () if soft == 0 else None
    setpriv = shutil.which("setpriv")
    # root without CAP_SYS_NICE in its bounding set (and RLIMIT_RTPRIO 0) is refused
    return (setpriv, "--bounding-set", "-sys_nice", "prlimit", "--rtprio=0") \
        if setpriv and shutil.which("prlimit") else None


def test_a_configured_priority_that_is_refused_blocks_the_config(tmp_path):
    prefix = _without_rt_rights()
    if prefix is None:
        pytest.skip("this user may use SCHED_FIFO and cannot drop the right")
    path = tmp_path / "robot.yaml"
    data = yaml.safe_load((EXAMPLES / "bench_vcan.yaml").read_text())
    data["bus"] = {"interface": "virtual", "channel": "doctor"}
    data["realtime"] = {"priority": 80}
    path.write_text(yaml.safe_dump(data))
    done = doctor(str(path), "--json", prefix=prefix)
    checks = {c["name"]: c for c in json.loads(done.stdout)}
    assert checks["bus doctor"]["status"] == "n/a"
    sched = checks["scheduler: SCHED_FIFO"]
    assert sched["status"] == "fail" and "realtime.priority 80 is refused" in sched["found"]
    assert "CAP_SYS_NICE" in sched["fix"] if os.getuid() == 0 else "rtprio" in sched["fix"]
    assert done.returncode == 1
