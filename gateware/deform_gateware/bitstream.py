"""deform's SoC on an ECP5 board, built into a bitstream with open tools.

    python -m deform_gateware.bitstream --board ulx3s --mvus N --out DIR [--seed S]
        [--router router1|router2] [--no-pnr | --place-only] [--nodes 512|1024]
        [--keep-out N] [--no-bus-bursting] [--global-reset]

The SoC is litex-boards' ULX3S target on an LFE5U-85F: a VexRiscv ``imac`` at 50 MHz, the
board's SDRAM as main RAM at 0x4000_0000, the stock LiteX BIOS in ROM (which loads the firmware
over the serial line: ``deform flash --protocol litex``), a UART, timer0 — and the MVU array of
this package with N MVUs (``mvu_array.add_to_soc``), the same registers and region as the
simulated SoC's.

LiteX writes the BIOS, the Verilog and the tools' scripts (``Builder.build(run=False)``); this
module then runs the three stages itself — Yosys, nextpnr-ecp5 (with its timing and utilisation
report) and ecppack, YoWASP's builds (PyPI wheels with the chip database) of the commands LiteX's
``trellis`` toolchain asks for — so that each stage is printed with its time, ``--no-pnr`` can
stop after Yosys, ``--place-only`` after placement, and no stage's process outlives this one.

Outputs, in DIR: gateware/*.bit and .svf, csr.json (for the firmware: DEFORM_LITEX_CSR_JSON),
each stage's log in gateware/, and report.json: Yosys's cell counts (LUT4, CCU2C, TRELLIS_FF,
MULT18X18D, DP16KD, ...), nextpnr's use of the device and the system clock's Fmax (``null`` with
``--no-pnr``), the stages run with their seconds, the MVUs' capacity and the gateware's commit.
report.json and the bitstream are removed before a build and written only by a build that got
that far, so neither is ever a stale or half-written file.

The SoC is built with LiteX's ``bus_bursting`` (issue 19), as the simulated SoC is: the CPU's
caches fill a line in one Wishbone incrementing burst where the slave supports it. On this board
that is the integrated ROM (the BIOS) and SRAM, LiteX's ``wishbone.SRAM`` with burst support;
the SDRAM's port (main RAM, where the firmware runs) is a plain Wishbone interface behind
LiteX's L2 cache (``wishbone.Cache``) and LiteDRAM's ``LiteDRAMWishbone2Native``, neither of
which reads CTI, so its line fills stay single accesses, as valid as before (a bursting master
on a classic slave gets one ack per word). ``--no-bus-bursting`` builds the SoC without it (the
earlier figures).

``--global-reset`` resets the MVU array's registers from the system reset through a DCCA, the
ECP5's global clock buffer, so that nextpnr routes that reset on a global network as it does the
clocks (``reset_on_global``), not through the general routing to 19,127 flip-flops (4 MVUs).
Measured in session 12 (docs/PERFORMANCE.md, "4 MVUs routed, session 12"): 12,609 fewer arcs to
route and a higher estimate after placement, but the 4-MVU SoC still did not route in the time
there was, so it is not the default. report.json's ``global_reset`` says which. It can also make a
design unroutable: where Yosys merges the reset with a register's synchronous set into one LSR
(the MVU's ``fresh``: ``mvu_rst | go``), the global net enters a LUT, and on the 2-MVU SoC (seed 1,
session 18) that left the LUT's other input with no path at all ("Failed to route arc"), while
the same SoC with the reset in the fabric routed.

nextpnr places in two runs by default (``keepout``): first with every third row of logic tiles
held by locked filler cells, so that its placer, whose density nextpnr 0.11 fixes for the ECP5,
spreads the SoC over the whole device; then, the fillers deleted from the placed netlist, it
routes that placement (``nextpnr-place.log``, ``nextpnr.log``). Without it the 4-MVU SoC never
routed (router2's overuse stalled near 20,000 wires, sessions 6-18); with it, router2 falls to
tens of wires, and with its bounding box widened (``ROUTER2_SETTINGS``) to none: the 4-MVU SoC
routes (session 19, docs/PERFORMANCE.md). ``--keep-out N`` holds every N-th row instead,
``--keep-out 0`` runs nextpnr's own flow in one run; report.json's ``keep_out`` says which.

nextpnr routes with its own default, ``router1``, or with ``--router router2``; the report names
the one used. On the SoC without MVUs router2 took 33 s against 319 and reached 42.9 MHz against
46.5; on the 4-MVU SoC neither finished on a 2-core machine (docs/PERFORMANCE.md).

``--place-only`` packs and places (nextpnr's ``--no-route``) and stops: the placement settles
whether a design fits the device and gives nextpnr's estimate of its Fmax after placement, where
routing a big SoC takes hours here. The report holds that estimate with ``routed: false`` (read
from nextpnr's log: its ``--report`` has no Fmax without routing); it is an estimate, never a
routed Fmax. No ``--textcfg`` is asked for (an unrouted design has no configuration to write),
so no bitstream either.

With more than four MVUs the MVUs get half the memories (512 rows, 2048 words). Meant to let
eight fit the LFE5U-85F's 208 block RAMs, it is not enough: Yosys counts 259 DP16KD for eight
(40 of them the SoC's own; docs/PERFORMANCE.md), counted before Kp and p's row copy took the
36-bit mode at 512 rows (``bram``). ``--nodes 512|1024`` asks for each MVU's rows of p and Kp
whatever the count: at 512, an MVU takes 24 DP16KD instead of 32 (4 MVUs: 139 of 208 instead of
173). The SoC's ``nodes`` register tells the firmware its rows; a model of more nodes is refused
by the program builder (its MVU phase runs in software), never run on too small a memory.
"""

import argparse
import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time

from litex.soc.integration.builder import Builder

from deform_gateware import keepout
from deform_gateware.mvu_array import add_to_soc
from deform_gateware.synth import log, placement_estimate, run_stage, summary, tool

BOARDS = ("ulx3s",)
SYS_CLK_FREQ = 50e6
REPORT = "nextpnr-report.json"
# nextpnr's routers; the first, nextpnr's own default, is this module's.
ROUTERS = ("router1", "router2")
# Yosys's cells the report keeps (synth_ecp5's final statistics).
YOSYS_CELLS = ("LUT4", "CCU2C", "TRELLIS_FF", "MULT18X18D", "ALU54B", "DP16KD",
               "TRELLIS_DPR16X4", "PFUMX", "L6MUX21")


# Every third row of logic tiles held while placing (``keepout``): router2's overuse on the 4-MVU
# SoC then falls to tens of wires, where without it it stalled near 20,000 (docs/PERFORMANCE.md,
# session 19), and the two thirds left hold the SoC (it takes 49 % of the LFE5U-85F's logic).
KEEP_OUT = 3

# The rows of p and Kp per MVU a build may ask for (``--nodes``): 1024 (the default up to four
# MVUs) or 512, where Kp and p's row copy take the block RAM's 36-bit pseudo-dual-port mode
# (``bram``): 24 DP16KD per MVU instead of 32.
NODES = (512, 1024)


def capacity(mvus, nodes=None):
    """(words, tiles, nodes) per MVU; ``nodes`` (one of ``NODES``) replaces the default rows.
    The SoC tells the firmware its rows (the array's ``nodes`` register), and the firmware's
    program builder refuses a model of more nodes (``ProgramError::DimensionTooLarge``: the MVU
    phase then runs in software), so a smaller build is never silently overrun."""
    words, tiles, rows = (4096, 256, 1024) if mvus <= 4 else (2048, 256, 512)
    if nodes is not None:
        if nodes not in NODES:
            raise SystemExit("--nodes %d: the MVUs are built with %s rows of p and Kp"
                             % (nodes, " or ".join(map(str, NODES))))
        rows = nodes
    return words, tiles, rows


def ulx3s_soc(mvus, nodes=None, bus_bursting=True, global_reset=False):
    from litex_boards.targets.radiona_ulx3s import BaseSoC
    soc = BaseSoC(device="LFE5U-85F", revision="2.0", toolchain="trellis",
                  sys_clk_freq=SYS_CLK_FREQ, cpu_type="vexriscv", cpu_variant="imac",
                  integrated_rom_size=0x20000, integrated_sram_size=0x2000,
                  with_led_chaser=False, bus_bursting=bus_bursting)
    words, tiles, nodes = capacity(mvus, nodes)
    add_to_soc(soc, mvus, words=words, tiles=tiles, nodes=nodes, primitive=True)
    if global_reset:
        reset_on_global(soc)
    return soc


def reset_on_global(soc):
    """The MVU array's reset through a DCCA, the ECP5's global clock buffer, so that nextpnr
    routes it on a global network, as it does the clocks, and not in the fabric.

    LiteX resets every register of the system clock domain synchronously from one flip-flop
    (the CRG's reset synchroniser), and nextpnr-ecp5 promotes only clocks to its global
    networks. With four MVUs that reset net reaches 19,929 pins (19,872 of them flip-flops'
    LSR; 19,127 the array's), from one driver to every corner of the device through the
    general routing. Here the array runs in a clock domain
    of its own, ``mvu``: the same clock (``sys``'s, one net), and ``sys``'s reset through a
    DCCA (clock enable tied high), which nextpnr places on a global network that reaches every
    tile's LSR multiplexers. The logic is unchanged: the same clock, the same synchronous
    reset, a buffer's delay later (nextpnr times that path as any other). Only this board's
    build does it: the simulated SoCs keep the array in ``sys``."""
    from migen import ClockDomain, ClockDomainsRenamer, ClockSignal, Instance, ResetSignal
    cd = ClockDomain("mvu")
    soc.clock_domains += cd
    soc.comb += cd.clk.eq(ClockSignal("sys"))
    soc.specials += Instance("DCCA", i_CLKI=ResetSignal("sys"), i_CE=1, o_CLKO=cd.rst)
    ClockDomainsRenamer("mvu")(soc.mvus)


def yosys_cells(rpt):
    """The cell counts of Yosys's last statistics in its log: both the newer layout
    (``   12207   LUT4``) and the older one (``   LUT4   12207``)."""
    with open(rpt) as f:
        text = f.read()
    last = text.rfind("Printing statistics")
    if last < 0:
        raise SystemExit("%s has no statistics: did Yosys finish?" % rpt)
    cells = {}
    for line in text[last:].splitlines():
        m = re.match(r"^\s+(\d+)\s+(\w+)\s*$", line) or re.match(r"^\s+(\w+)\s+(\d+)\s*$", line)
        if not m:
            continue
        count, name = (m.group(1), m.group(2)) if m.group(1).isdigit() else (m.group(2), m.group(1))
        if name in YOSYS_CELLS and name not in cells:
            cells[name] = int(count)
    return {name: cells.get(name, 0) for name in YOSYS_CELLS}


def gateware_commit():
    """The commit of this package's sources (``+dirty`` if they differ from it), so a figure can
    be tied to the MVU it measured."""
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=here, check=True,
                              capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "."], cwd=here, check=True,
                               capture_output=True, text=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("+dirty" if dirty else "")


def write_atomic(path, text):
    part = os.path.join(os.path.dirname(path), "." + os.path.basename(path) + ".part")
    with open(part, "w") as f:
        f.write(text)
    os.replace(part, path)


def remove(*paths):
    for path in paths:
        if os.path.exists(path):
            os.remove(path)


def tool_argv(command):
    """A LiteX toolchain command line with its program replaced by YoWASP's build of it."""
    argv = shlex.split(command)
    return [tool(argv[0])] + argv[1:]


def place_only_argv(argv):
    """nextpnr's command line placing and not routing: ``--no-route``, and without
    ``--textcfg FILE`` (there is no routed design to write)."""
    kept = []
    it = iter(argv)
    for arg in it:
        if arg == "--textcfg":
            next(it, None)
        elif not arg.startswith("--textcfg="):
            kept.append(arg)
    return kept + ["--no-route"]


def place_and_route(args, argv, gateware, stages):
    """nextpnr's own flow, one run (placing only with ``--place-only``); returns its report
    and, for a placement, its estimate of the Fmax."""
    if args.place_only:
        argv = place_only_argv(argv)
    else:
        argv = argv + ["--router", args.router]
    stages["nextpnr"] = run_stage("nextpnr-ecp5", argv, gateware, "nextpnr.log")
    estimate = None
    if args.place_only:
        with open(os.path.join(gateware, "nextpnr.log")) as f:
            estimate = placement_estimate(f.read())
    with open(os.path.join(gateware, REPORT)) as f:
        return json.load(f), estimate


# router2's bounding box around each net widened from 3 tiles to 8 (its settings, read only by
# router2): on the kept-out 4-MVU SoC router2 then reached no overused wire (seed 1, 67 passes),
# where with 3 it fell to 18 and turned back up (docs/PERFORMANCE.md, session 19). Bare values:
# nextpnr cannot read a number with a trailing space.
ROUTER2_SETTINGS = {"router2/bbMargin/x": "8", "router2/bbMargin/y": "8"}

# The netlists of a kept-out build (filled, placed, routable): deleted when it ends, and before a
# build (a build killed outright, SIGKILL, leaves them).
KEPT_OUT_NETLISTS = ("-keepout.json", "-placed.json", "-routable.json")


def json_argv(argv, path):
    """nextpnr's command line reading the netlist ``path`` instead of its ``--json FILE``."""
    out = list(argv)
    out[out.index("--json") + 1] = path
    return out


def kept_out_place_and_route(args, argv, gateware, name, stages):
    """Two nextpnr runs (``keepout``): the netlist placed with every ``--keep-out``-th row of
    logic tiles held by fillers, then the placement, fillers deleted, routed. Returns the
    report (the device's use without the fillers) and, for ``--place-only``, the estimate."""
    filled, placed, routable = (name + suffix for suffix in KEPT_OUT_NETLISTS)
    netlist = keepout.load(os.path.join(gateware, name + ".json"))
    tiles = keepout.logic_tiles(keepout.load(keepout.tilegrid_path()))
    rows, fillers = keepout.add(netlist, tiles, args.keep_out)
    keepout.save(netlist, os.path.join(gateware, filled))
    del netlist
    log("    keep-out: %d rows of logic tiles held while placing (%d filler cells)"
        % (rows, fillers))
    try:
        place = place_only_argv(json_argv(argv, filled)) + ["--write", placed]
        stages["nextpnr-place"] = run_stage("nextpnr-ecp5, placement", place, gateware,
                                            "nextpnr-place.log")
        if args.place_only:
            with open(os.path.join(gateware, "nextpnr-place.log")) as f:
                estimate = placement_estimate(f.read())
            with open(os.path.join(gateware, REPORT)) as f:
                return without_fillers(json.load(f), fillers), estimate
        design = keepout.load(os.path.join(gateware, placed))
        keepout.remove(design)
        settings = keepout.top_module(design).setdefault("settings", {})
        # The placed netlist's settings win over the command line's.
        settings.update({"router": args.router, "target_freq": "%f" % SYS_CLK_FREQ},
                        **ROUTER2_SETTINGS)
        keepout.save(design, os.path.join(gateware, routable))
        del design
        route = json_argv(argv, routable) + ["--no-pack", "--no-place", "--router", args.router]
        stages["nextpnr-route"] = run_stage("nextpnr-ecp5, routing", route, gateware,
                                            "nextpnr.log")
        with open(os.path.join(gateware, REPORT)) as f:
            return json.load(f), None
    finally:
        remove(*(os.path.join(gateware, f) for f in (filled, placed, routable)))


def without_fillers(report, fillers):
    """A placement's report with the keep-out fillers (half LUT4s, half flip-flops) taken out
    of the use of the device."""
    used = report["utilization"]
    for cell in ("TRELLIS_COMB", "TRELLIS_FF"):
        used[cell]["used"] -= fillers // 2
    return report


def build(args, out):
    """Runs the stages; returns report.json's content."""
    commit = gateware_commit()  # before the build: the sources it reads
    stages = {}
    log("--> LiteX: the SoC, its BIOS, the Verilog and the tools' scripts")
    started = time.monotonic()
    soc = ulx3s_soc(args.mvus, args.nodes, bus_bursting=not args.no_bus_bursting,
                    global_reset=args.global_reset)
    gateware = os.path.join(out, "gateware")
    name = soc.platform.name
    bitstream = os.path.join(gateware, name + ".bit")
    remove(os.path.join(out, "report.json"), bitstream, os.path.join(gateware, name + ".svf"),
           os.path.join(gateware, REPORT),
           *(os.path.join(gateware, name + suffix) for suffix in KEPT_OUT_NETLISTS))
    builder = Builder(soc, output_dir=out, csr_json=os.path.join(out, "csr.json"))
    builder.build(run=False, seed=args.seed)
    stages["litex"] = round(time.monotonic() - started, 1)
    log("    litex: %.0f s" % stages["litex"])
    # The commands LiteX's trellis toolchain would run (its script, build_NAME.sh, holds the
    # same): private attributes, as LiteX exposes no other way to have them one by one.
    toolchain = soc.platform.toolchain
    stages["yosys"] = run_stage("yosys", tool_argv(toolchain._yosys.get_yosys_call("script")),
                                gateware, "yosys.log")
    report = dict(board=args.board, mvus=args.mvus, seed=args.seed, router=args.router,
                  bus_bursting=not args.no_bus_bursting, global_reset=args.global_reset,
                  keep_out=args.keep_out,
                  commit=commit,
                  yosys=yosys_cells(os.path.join(gateware, name + ".rpt")), pnr=None,
                  bitstream=None, stages=stages)
    report.update(zip(("words", "tiles", "nodes"), capacity(args.mvus, args.nodes)))
    if args.no_pnr:
        log("    --no-pnr: nextpnr-ecp5 and ecppack not run (no Fmax, no bitstream)")
        return report
    pnr = tool_argv(toolchain._nextpnr.get_call("script")) + ["--report", REPORT]
    if args.keep_out:
        placed, estimate = kept_out_place_and_route(args, pnr, gateware, name, stages)
    else:
        placed, estimate = place_and_route(args, pnr, gateware, stages)
    report["pnr"] = summary(placed, SYS_CLK_FREQ / 1e6, estimate)
    if args.place_only:
        log("    --place-only: placed, not routed; nextpnr's estimate after placement %.1f MHz "
            "(no bitstream)" % report["pnr"]["fmax_mhz"])
        return report
    try:
        stages["ecppack"] = run_stage(
            "ecppack", tool_argv("%s %s" % (toolchain.packer_cmd, toolchain._packer_opts)),
            gateware, "ecppack.log")
    except BaseException:
        remove(bitstream, os.path.join(gateware, name + ".svf"))
        raise
    report["bitstream"] = bitstream
    return report


def keep_out_rows(text):
    """``--keep-out``'s value: 0 (off) or a period of at least 2 rows."""
    try:
        every = int(text)
    except ValueError:
        every = -1
    if every != 0 and every < 2:
        raise argparse.ArgumentTypeError(
            "%r: 0 (no rows held) or every N-th row, N at least 2" % text)
    return every


def arguments():
    """The command line's parser."""
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--board", choices=BOARDS, default="ulx3s")
    parser.add_argument("--mvus", type=int, required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--nodes", type=int, default=None,
                        help="rows of p and Kp per MVU: %s (default: 1024 up to four MVUs, "
                             "else 512)" % " or ".join(map(str, NODES)))
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--router", choices=ROUTERS, default=ROUTERS[0],
                        help="nextpnr's router (default %(default)s, nextpnr's own; none "
                             "with --place-only, which does not route)")
    parser.add_argument("--no-bus-bursting", action="store_true",
                        help="the SoC without Wishbone burst cycles (LiteX's bus_bursting off; "
                             "the default has them)")
    depth = parser.add_mutually_exclusive_group()
    depth.add_argument("--no-pnr", action="store_true",
                       help="stop after Yosys: cell counts only, no place and route, no Fmax, "
                            "no bitstream")
    depth.add_argument("--place-only", action="store_true",
                       help="pack and place, do not route (nextpnr's --no-route): the placement "
                            "settles whether the design fits and gives nextpnr's Fmax estimate "
                            "after placement (not a routed Fmax), where routing a big SoC takes "
                            "hours; no bitstream")
    parser.add_argument("--keep-out", type=keep_out_rows, default=KEEP_OUT, metavar="N",
                        help="place with every N-th row of logic tiles held free (locked "
                             "filler cells, deleted before routing), so that nextpnr spreads "
                             "the design over the device, and route with router2's bounding "
                             "box widened to 8 tiles (default %(default)s; 0: nextpnr's own "
                             "flow in one run, which packs a 4-MVU SoC too densely to route)")
    parser.add_argument("--global-reset", action="store_true",
                        help="the MVU array's reset on a global network through a DCCA "
                             "(reset_on_global), not in the general routing")
    return parser


def main():
    args = arguments().parse_args()
    out = os.path.abspath(args.out)
    if out.startswith("/tmp/"):
        raise SystemExit("--out must not be under /tmp (YoWASP's sandbox has its own /tmp)")
    os.makedirs(out, exist_ok=True)
    # A SIGTERM ends the build as Ctrl-C does: through the stages' clean-up.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    # This environment's Python first (the BIOS build runs `python3 -m litex...`).
    os.environ["PATH"] = os.pathsep.join([os.path.dirname(sys.executable),
                                          os.environ.get("PATH", "")])
    try:
        report = build(args, out)
    except KeyboardInterrupt:
        # The running stage's tool is killed by then (run_stage); no report, no bitstream.
        log("bitstream: interrupted")
        return 130
    text = json.dumps(report)
    write_atomic(os.path.join(out, "report.json"), json.dumps(report, indent=1))
    print(text)


if __name__ == "__main__":
    sys.exit(main())
