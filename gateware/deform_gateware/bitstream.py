"""deform's SoC on an ECP5 board, built into a bitstream with open tools.

    python -m deform_gateware.bitstream --board ulx3s --mvus N --out DIR [--seed S]

The SoC is litex-boards' ULX3S target on an LFE5U-85F: a VexRiscv ``imac`` at 50 MHz, the
board's SDRAM as main RAM at 0x4000_0000, the stock LiteX BIOS in ROM (which loads the firmware
over the serial line: ``deform flash --protocol litex``), a UART, timer0 — and the MVU array of
this package with N MVUs (``mvu_array.add_to_soc``), the same registers and region as the
simulated SoC's. LiteX's ``trellis`` toolchain runs Yosys, nextpnr-ecp5 and ecppack by name;
here they are YoWASP's (PyPI wheels with the chip database), through wrapper scripts in
DIR/bin, and nextpnr also writes its timing and utilisation report.

It writes DIR/gateware/*.bit (and .svf), DIR/csr.json (for the firmware: DEFORM_LITEX_CSR_JSON)
and DIR/report.json, and prints that report: LUT4s, flip-flops, MULT18X18D and DP16KD used and
available, the system clock's Fmax, the MVUs' capacity.

With more than four MVUs the MVUs get half the memories (512 rows, 2048 words), so that eight
fit the LFE5U-85F's 208 block RAMs beside the SoC's (BIOS ROM and caches: about 55).
"""

import argparse
import json
import os
import stat
import sys

from litex.soc.integration.builder import Builder

from deform_gateware.mvu_array import add_to_soc
from deform_gateware.synth import summary, tool

BOARDS = ("ulx3s",)
SYS_CLK_FREQ = 50e6
REPORT = "nextpnr-report.json"


def capacity(mvus):
    """(words, tiles, nodes) per MVU."""
    return (4096, 256, 1024) if mvus <= 4 else (2048, 256, 512)


def wrappers(out):
    """DIR/bin/{yosys,nextpnr-ecp5,ecppack}, exec'ing the YoWASP tools (nextpnr with a report)."""
    folder = os.path.join(out, "bin")
    os.makedirs(folder, exist_ok=True)
    extra = {"nextpnr-ecp5": " --report " + REPORT}
    for name in ("yosys", "nextpnr-ecp5", "ecppack"):
        path = os.path.join(folder, name)
        with open(path, "w") as f:
            f.write('#!/bin/sh\nexec "%s" "$@"%s\n' % (tool(name), extra.get(name, "")))
        os.chmod(path, os.stat(path).st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    return folder


def ulx3s_soc(mvus):
    from litex_boards.targets.radiona_ulx3s import BaseSoC
    soc = BaseSoC(device="LFE5U-85F", revision="2.0", toolchain="trellis",
                  sys_clk_freq=SYS_CLK_FREQ, cpu_type="vexriscv", cpu_variant="imac",
                  integrated_rom_size=0x20000, integrated_sram_size=0x2000,
                  with_led_chaser=False)
    words, tiles, nodes = capacity(mvus)
    add_to_soc(soc, mvus, words=words, tiles=tiles, nodes=nodes, primitive=True)
    return soc


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--board", choices=BOARDS, default="ulx3s")
    parser.add_argument("--mvus", type=int, required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    out = os.path.abspath(args.out)
    if out.startswith("/tmp/"):
        raise SystemExit("--out must not be under /tmp (YoWASP's sandbox has its own /tmp)")
    os.makedirs(out, exist_ok=True)
    # The tools' wrappers first, then this environment's Python (the BIOS build runs
    # `python3 -m litex...`).
    os.environ["PATH"] = os.pathsep.join(
        [wrappers(out), os.path.dirname(sys.executable), os.environ.get("PATH", "")])
    soc = ulx3s_soc(args.mvus)
    builder = Builder(soc, output_dir=out, csr_json=os.path.join(out, "csr.json"))
    builder.build(seed=args.seed)
    with open(os.path.join(out, "gateware", REPORT)) as f:
        report = summary(json.load(f), SYS_CLK_FREQ / 1e6)
    words, tiles, nodes = capacity(args.mvus)
    report.update(board=args.board, mvus=args.mvus, seed=args.seed, words=words, tiles=tiles,
                  nodes=nodes, bitstream=os.path.join(out, "gateware", soc.platform.name + ".bit"))
    with open(os.path.join(out, "report.json"), "w") as f:
        json.dump(report, f, indent=1)
    print(json.dumps(report))


if __name__ == "__main__":
    sys.exit(main())
