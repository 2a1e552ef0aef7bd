#!/usr/bin/env python3
"""Generates deform's LiteX SoC for Verilator: a VexRiscv CPU, main RAM, a UART, timer0 and the
MVU array of gateware/ (0 to 8 hardware MVUs, ``--mvus``).

Run by deform-hil-sim (src/litex.rs) inside the project's own virtual environment, once per SoC
configuration: the output folder is keyed by a hash of this file and of the arguments, so a
changed SoC gets a new folder and an unchanged one is never regenerated.

Two shapes:

- without --bios (the HIL target): no ROM, the CPU resets into main RAM, whose init file
  (gateware/sim_main_ram.init) is rewritten with each new firmware image, no re-Verilating;
- with --bios: the stock litex_sim SoC with its ROM and the stock LiteX BIOS, which waits for a
  serial boot (SFL) before its prompt; `deform flash --protocol litex` loads the firmware
  through it.

The UART's simulator module is LiteX's serial2tcp with one change, made here at build time (no
LiteX code is kept in the repository): it reads from the socket only what its 2048-byte ring
buffer can take. The stock module reads regardless and overwrites unconsumed bytes, so a host
with more than 2 KiB in flight saw corrupt frames; bounded, the rest waits in the socket (TCP
flow control reaches back through socat to the host's writes).

Every SoC it makes (either shape) has the same CSR map (ctrl, identifier, mvus, timer0, uart; no sim_debug
registers) and the MVU array's region at the same address, whatever ``--mvus`` says (0 included:
the array's registers then report no MVUs), so one firmware build runs on all of them and reads
the number of MVUs and their capacity from the array's registers at boot. The script only
writes the gateware and build_sim.sh; the caller runs that (the Verilator build) and the
simulator itself.

Bus bursting (issue 19) is on by default: the CPU's caches fill a line in one Wishbone burst
(CTI incrementing) from main RAM instead of one single access per word (LiteX's
``bus_bursting``: the integrated RAMs accept bursts). ``--no-bus-bursting`` builds the SoC
without it, so the earlier, non-bursting figures stay reproducible. The CSR map does not change
(csr.json's constant ``config_bus_bursting`` does: 1, or 0 without).

With --uart-baud (on by default for the BIOS shape) the module also paces what it hands the
SoC: one received byte per sys_clk/(baud/10) clocks, as a UART at that baud rate would, instead
of one per clock. The stock BIOS's interrupt handler moves every byte into a 128-byte ring that
its serial boot empties far slower than one byte per clock, so an unpaced line overflowed it
under litex_term's 128 frames in flight (`Got unexpected response from device 'E'`); a real
board's line is slow enough. Bytes to the host are not paced.
"""

import argparse
import os
import sys

import litex.build.sim

from litex.build.sim.config import SimConfig
from litex.soc.integration.builder import Builder
from litex.tools.litex_sim import SimSoC

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "gateware"))
from deform_gateware.mvu_array import add_to_soc  # noqa: E402


FLOW_MODULE = "serial2tcp_flow"

# The simulated MVUs' capacity: n up to 4096 (a 16³ grid), 32 Ki words and 512 tiles per MVU.
MVUS_NODES = 4096
MVUS_WORDS = 32768
MVUS_TILES = 512


# The SoC's nominal clock (litex_sim's): the UART pacing counts its cycles.
SYS_CLK_HZ = int(1e6)

# The BIOS shape's default line rate. At the SoC's nominal 1 MHz, 9,600 baud gives the BIOS 1,042
# cycles per received byte (a 100 MHz board has 868 at 115,200 baud). Measured with stock
# litex_term's default mode (hil-sim/tests/hil/bios_boot.rs): at 38,400 baud (260 cycles) its
# upload failed in both of two runs (a CRC error, then an unexpected `E`: the BIOS's receive ring
# overflowed); at 9,600 it booted the 155 KB image in both of two runs (0.2-0.4 KB/s in a loaded
# simulation). deform's own SFL client keeps one frame in flight and runs faster (hil-sim's
# LitexConfig::uart_pace).
BIOS_UART_BAUD = 9600


def pace_rx(source):
    """serial2tcp handing the SoC at most one byte per `pace` clocks, `pace` being a module
    argument in sim_config.js (0 or absent: one per clock, as the stock module)."""
    patches = [
        (
            "  int fd;\n};",
            "  int fd;\n  int pace; /* deform: clocks per received byte */\n"
            "  int pause; /* clocks until the next byte may go in */\n};",
        ),
        (
            "  memset(s, 0, sizeof(struct session_s));\n",
            "  memset(s, 0, sizeof(struct session_s));\n"
            "  if(RC_OK == litex_sim_module_get_args(args, \"pace\", &cport) && cport) {\n"
            "    sscanf(cport, \"%d\", &s->pace);\n"
            "    free(cport);\n"
            "  }\n",
        ),
        (
            "  *s->rx_valid=0;\n  if(s->datalen) {",
            "  *s->rx_valid=0;\n  if(s->pause) {\n    s->pause--;\n  } else if(s->datalen) {",
        ),
        (
            "      s->datalen--;\n",
            "      s->datalen--;\n      s->pause = s->pace > 1 ? s->pace - 1 : 0;\n",
        ),
    ]
    for old, new in patches:
        if source.count(old) != 1:
            raise SystemExit("serial2tcp.c is not the version this script paces")
        source = source.replace(old, new)
    return source


def write_flow_module(out):
    """serial2tcp, reading no more than its ring buffer has room for, pacing (see above)."""
    core = os.path.join(os.path.dirname(litex.build.sim.__file__), "core", "modules", "serial2tcp")
    with open(os.path.join(core, "serial2tcp.c")) as f:
        source = f.read()
    unbounded = "read_len = read(fd, buffer, 1024);"
    bounded = (
        "if (s->datalen >= 2048) return; /* full: leave the rest in the socket */\n"
        "  read_len = read(fd, buffer, (2048 - s->datalen) < 1024 ? (2048 - s->datalen) : 1024);"
    )
    name = '"serial2tcp",'
    if source.count(unbounded) != 1 or source.count(name) != 1:
        raise SystemExit("serial2tcp.c is not the version this script patches")
    source = source.replace(unbounded, bounded).replace(name, '"%s",' % FLOW_MODULE)
    source = pace_rx(source)
    folder = os.path.join(out, "extra_mods")
    os.makedirs(os.path.join(folder, FLOW_MODULE), exist_ok=True)
    with open(os.path.join(folder, FLOW_MODULE, FLOW_MODULE + ".c"), "w") as f:
        f.write(source)
    with open(os.path.join(core, "Makefile")) as f:
        makefile = f.read()
    with open(os.path.join(folder, FLOW_MODULE, "Makefile"), "w") as f:
        f.write(makefile)
    return folder


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--cpu-variant", default="imac", help="VexRiscv variant (imac reads mcycle)")
    parser.add_argument("--main-ram-size", type=lambda s: int(s, 0), default=0x200000)
    parser.add_argument("--bios", action="store_true", help="ROM with the stock LiteX BIOS")
    parser.add_argument("--mvus", type=int, default=0, help="hardware MVUs (0 to 8)")
    parser.add_argument(
        "--no-bus-bursting",
        action="store_true",
        help="no Wishbone burst cycles: a cache line fills by one single access per word (by "
        "default it fills in one incrementing burst from main RAM)",
    )
    parser.add_argument(
        "--uart-baud",
        type=int,
        default=None,
        help="pace received bytes at this baud rate (0: one per clock; default: %d with --bios, "
        "else 0)" % BIOS_UART_BAUD,
    )
    args = parser.parse_args()
    baud = args.uart_baud if args.uart_baud is not None else (BIOS_UART_BAUD if args.bios else 0)
    pace_cycles = round(SYS_CLK_HZ * 10 / baud) if baud else 0

    soc_args = dict(
        cpu_type="vexriscv",
        cpu_variant=args.cpu_variant,
        uart_name="sim",
        integrated_sram_size=0x2000,
        integrated_main_ram_size=args.main_ram_size,
        bus_bursting=not args.no_bus_bursting,
    )
    if args.bios:
        # litex_sim's default ROM; the BIOS and its picolibc are built into it.
        soc_args.update(integrated_rom_size=0x20000)
    else:
        soc_args.update(
            integrated_rom_size=0,
            cpu_reset_address=0x40000000,
            # All zero, but present: the RAM then reads its contents from sim_main_ram.init,
            # which the caller rewrites for every firmware.
            integrated_main_ram_init=[0] * (args.main_ram_size // 4),
        )
    soc = SimSoC(**soc_args)
    add_to_soc(soc, args.mvus, words=MVUS_WORDS, tiles=MVUS_TILES, nodes=MVUS_NODES)
    if args.bios:
        # No memory test of main RAM at boot (2 MiB written and read back: tens of seconds of
        # simulation before the BIOS asks for a serial boot); the BIOS skips it when told that
        # main RAM was initialised.
        soc.add_config("MAIN_RAM_INIT")

    sim_config = SimConfig()
    sim_config.add_clocker("sys_clk", freq_hz=SYS_CLK_HZ)
    # The port is a placeholder: the caller writes sim_config.js anew for every run (the pace
    # stays; it comes first, so that the placeholder's line is the last of the arguments).
    sim_config.add_module(FLOW_MODULE, "serial", args={"pace": pace_cycles, "port": 1})

    builder = Builder(
        soc,
        output_dir=args.out,
        compile_software=args.bios,
        csr_json=os.path.join(args.out, "csr.json"),
    )
    out = os.path.abspath(args.out)
    os.makedirs(out, exist_ok=True)
    builder.build(
        sim_config=sim_config,
        run=False,
        extra_mods=[FLOW_MODULE],
        extra_mods_path=write_flow_module(out),
    )


if __name__ == "__main__":
    main()
