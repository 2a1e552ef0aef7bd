#!/usr/bin/env python3
"""deform_soc.py's SoC with the VexRiscv pipeline probe, for Verilator traces (issue 19).

Takes deform_soc.py's arguments and builds the same SoC (same CSR map, same memory), with two
additions:

- deform_trace_probe.v copies the VexRiscv's pipeline arbitration, hazard and bus signals out
  of the CPU, whose own signals are not traced (deform_trace.vlt, written into the output
  folder), so a trace holds the probe's ~30 and the SoC top's ~700 signals, not the CPU's
  thousands;
- the probe drives the SoC's `sim_trace` pin, which gates LiteX's dump, from a window that each
  run reads from trace_window.init in the simulator's working folder (see the probe's header):
  one Verilated SoC traces any window of any firmware. The simulator writes sim.vcd there.

A separate script rather than a flag of deform_soc.py: hil-sim keys every SoC build by the text
of its generator, so a change there would invalidate every cached untraced SoC.
"""

import os
import sys

from migen import ClockSignal, Instance
from migen.fhdl.structure import _Assign
from litex.soc.integration.builder import Builder

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import deform_soc  # noqa: E402

# Verilator configuration: no trace of the CPU's own ~6,000 lines (the probe copies what the
# analysis needs). The SoC's top module (sim.v, ~700 signals) stays traced: with it off, the
# probe below it is not traced either (tried: an empty trace).
TRACE_VLT = """`verilator_config
tracing_off -file "*/VexRiscv*.v"
"""


def out_folder(argv):
    """deform_soc.py's --out argument (required there)."""
    for i, arg in enumerate(argv):
        if arg == "--out" and i + 1 < len(argv):
            return os.path.abspath(argv[i + 1])
        if arg.startswith("--out="):
            return os.path.abspath(arg[len("--out="):])
    raise SystemExit("deform_soc_trace.py: --out is required")


def main():
    out = out_folder(sys.argv)
    os.makedirs(out, exist_ok=True)
    vlt = os.path.join(out, "deform_trace.vlt")
    with open(vlt, "w") as f:
        f.write(TRACE_VLT)
    add_array = deform_soc.add_to_soc

    def add_array_and_probe(soc, *args, **kwargs):
        add_array(soc, *args, **kwargs)
        # litex_sim's SimSoC ties sim_trace to 1 (dump always) when it has no sim_debug CSRs:
        # the probe drives it instead.
        trace = soc.platform.trace
        fragment = soc._fragment
        tied = [s for s in fragment.comb if isinstance(s, _Assign) and s.l is trace]
        if len(tied) != 1:
            raise SystemExit("deform_soc_trace.py: litex_sim no longer ties sim_trace as expected")
        fragment.comb = [s for s in fragment.comb if s is not tied[0]]
        soc.platform.add_source(vlt, language="verilog")
        soc.platform.add_source(os.path.join(HERE, "deform_trace_probe.v"), language="verilog")
        soc.specials += Instance(
            "deform_trace_probe", i_clk=ClockSignal("sys"), o_trace_on=trace
        )

    build = Builder.build

    def traced_build(self, *args, **kwargs):
        kwargs["trace"] = True
        return build(self, *args, **kwargs)

    deform_soc.add_to_soc = add_array_and_probe
    Builder.build = traced_build
    deform_soc.main()


if __name__ == "__main__":
    main()
