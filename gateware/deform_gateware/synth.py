"""One MVU alone, synthesised for an ECP5 with open tools (YoWASP's Yosys and nextpnr-ecp5 from
PyPI), out of context: does it fit an LFE5U-85F and close timing at the thesis's 133 MHz?

    python -m deform_gateware.synth --out DIR [--size full|ci] [--freq 133] [--speed 6] [--seed 1]

writes DIR/mvu.v (Migen's Verilog of ``mvu.Mvu``), DIR/mvu.json (Yosys), DIR/report.json
(nextpnr's timing and utilisation) and prints a summary as one JSON object on stdout: LUT4s,
flip-flops, MULT18X18D and DP16KD used and available, Fmax, and whether it fits and meets the
frequency. Every port of the unit is a port of the design (``--out-of-context``: no I/O pads),
so nothing is optimised away that the MVU array would use.

The tools run in YoWASP's sandbox, where /tmp is private (an absolute path under /tmp would
name the sandbox's own): every path handed to them is relative to DIR, their working directory,
which the sandbox maps as it is, so DIR may be anywhere, /tmp included.
"""

import argparse
import ctypes
import json
import os
import re
import signal
import subprocess
import sys
import time

from migen.fhdl.verilog import convert

from deform_gateware.mvu import Mvu

# The LFE5U-85F in the ULX3S's package.
DEVICE = ["--85k", "--package", "CABGA381"]
# The MVU's capacity in the ECP5 builds (bitstream.py uses the same for up to four MVUs).
WORDS, TILES, NODES = 4096, 256, 1024
# Capacities by name: ``full`` is the ECP5 builds' (the benchmark in docs/PERFORMANCE.md);
# ``ci`` is the gate's check, the same unit and pipeline with a smaller word memory and tile
# table (1,024 words, 16 tiles; p and Kp keep their 1,024 rows, so every block RAM, multiplier
# and row compare is the full unit's). Measured at seed 1: ~700 LUT4 (the full tile table's
# 16-way read multiplexer) and 7 DP16KD fewer; its place and route was not much shorter here
# (255-358 s against 250-325 s for the full size at a similar load).
SIZES = {"full": (WORDS, TILES, NODES), "ci": (1024, 16, NODES)}


def tool(name):
    """A YoWASP tool from the Python environment running this script."""
    return os.path.join(os.path.dirname(sys.executable), "yowasp-" + name)


def unit_ports(unit):
    ports = {unit.start, unit.last_row, unit.directions, unit.length, unit.busy, unit.stalls}
    ports |= set(unit.p_kp_low) | set(unit.p_kp_high) | set(unit.kp_or)
    for port in (unit.bus_word, unit.bus_tile, unit.bus_p, unit.bus_kp):
        ports |= {port.adr, port.dat_r, port.dat_w, port.we}
    return ports


def log(message):
    print(message, file=sys.stderr, flush=True)


def _die_with_parent():
    """In the forked tool, before exec: the kernel SIGKILLs it when this process dies, however
    it dies (a SIGKILL included), so no Yosys or nextpnr runs on after an interrupted build."""
    libc = ctypes.CDLL(None, use_errno=True)
    pr_set_pdeathsig = 1
    libc.prctl(pr_set_pdeathsig, signal.SIGKILL)


def run_stage(name, argv, cwd, logfile):
    """Runs one tool with its output in cwd/logfile; prints the stage and its seconds. On an
    interrupt the tool is killed and waited for before the exception goes on."""
    log("--> %s (log: %s)" % (name, os.path.join(cwd, logfile)))
    started = time.monotonic()
    with open(os.path.join(cwd, logfile), "w") as f, \
            subprocess.Popen(argv, cwd=cwd, stdout=f, stderr=subprocess.STDOUT,
                             stdin=subprocess.DEVNULL, preexec_fn=_die_with_parent) as p:
        try:
            status = p.wait()
        except BaseException:
            p.kill()
            p.wait()  # Popen's own exit skips the wait on a KeyboardInterrupt
            raise
    seconds = round(time.monotonic() - started, 1)
    if status != 0:
        with open(os.path.join(cwd, logfile)) as f:
            tail = "".join(f.readlines()[-30:])
        raise SystemExit("%s failed (exit %d) after %.0f s; the end of %s:\n%s"
                         % (name, status, seconds, logfile, tail))
    log("    %s: %.0f s" % (name, seconds))
    return seconds


def summary(report, freq, estimate=None):
    """nextpnr's report, as the builds keep it: the use of the device and the slowest clock's
    Fmax. ``estimate``: for a design placed and not routed (``--no-route``), whose report has
    no Fmax, nextpnr's estimate after placement, read from its log (``placement_estimate``);
    the result then says ``routed: false``."""
    used = report["utilization"]
    if estimate is None:
        fmax = min(v["achieved"] for v in report["fmax"].values())
    else:
        fmax = estimate

    def count(cell):
        u = used.get(cell, {"used": 0, "available": 0})
        return {"used": u["used"], "available": u["available"]}

    cells = {name: count(cell) for name, cell in
             [("lut4", "TRELLIS_COMB"), ("ff", "TRELLIS_FF"), ("mult18x18d", "MULT18X18D"),
              ("dp16kd", "DP16KD")]}
    fits = all(c["used"] <= c["available"] for c in cells.values())
    return dict(cells, fmax_mhz=round(fmax, 1), target_mhz=freq, fits=fits,
                meets_timing=fmax >= freq, routed=estimate is None)


# nextpnr's line for a clock's Fmax, printed after placement and after routing alike:
# ``Info: Max frequency for clock '$glbnet$crg_clkout': 37.51 MHz (FAIL at 50.00 MHz)``, the
# name padded with spaces when several clocks are listed.
MAX_FREQUENCY = re.compile(r"Max frequency for clock +'([^']*)': ([0-9.]+) MHz")


def placement_estimate(log_text):
    """The slowest clock's Fmax in the last timing analysis of a nextpnr log (MHz): for a run
    with ``--no-route``, nextpnr's estimate after placement, which its ``--report`` leaves out
    (nextpnr 0.11 keeps only the router's analysis there). Each clock's last line counts."""
    last = {}
    for clock, mhz in MAX_FREQUENCY.findall(log_text):
        last[clock] = float(mhz)
    if not last:
        raise SystemExit("nextpnr's log has no \"Max frequency for clock\" line: "
                         "did the placement finish?")
    return min(last.values())


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--size", choices=sorted(SIZES), default="full")
    parser.add_argument("--freq", type=float, default=133.0)
    parser.add_argument("--speed", default="6")
    parser.add_argument("--seed", default="1")
    args = parser.parse_args()
    out = os.path.abspath(args.out)
    os.makedirs(out, exist_ok=True)
    words, tiles, nodes = SIZES[args.size]
    unit = Mvu(words, tiles, nodes, primitive=True)
    convert(unit, ios=unit_ports(unit), name="mvu").write(os.path.join(out, "mvu.v"))
    run_stage("yosys", [tool("yosys"), "-q", "-p",
                        "read_verilog mvu.v; synth_ecp5 -top mvu -json mvu.json; "
                        "tee -o yosys_stat.txt stat"], out, "yosys.log")
    run_stage("nextpnr-ecp5", [tool("nextpnr-ecp5")] + DEVICE + [
        "--speed", args.speed, "--freq", str(args.freq), "--seed", args.seed,
        "--json", "mvu.json", "--out-of-context", "--timing-allow-fail",
        "--report", "report.json"], out, "nextpnr.log")
    with open(os.path.join(out, "report.json")) as f:
        result = summary(json.load(f), args.freq)
    result.update(words=words, tiles=tiles, nodes=nodes, speed=args.speed, seed=args.seed)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
