"""The vectors of the gateware's unit tests, computed by target-core's portable kernel.

A Rust test (``hil-sim/tests/hil/gateware.rs``) writes them and runs these tests with
``DEFORM_MVU_VECTORS`` naming the file; nothing here computes an expected value itself. Each
case is a program as ``target-core/src/mvu_program.rs`` lays it out (per MVU its words with
their flags, its tiles and length; the owner of every row; the shared rows) and one or more
phases (p, the fused directions, and the kernel's Kp, pᵀKp and OR of |Kp|).
"""

import json
import os

VECTORS_ENV = "DEFORM_MVU_VECTORS"

MASK32 = (1 << 32) - 1
MASK64 = (1 << 64) - 1


def load():
    path = os.environ.get(VECTORS_ENV)
    if not path:
        raise RuntimeError(
            "%s is not set: run these tests through `cargo test -p deform-hil-sim --test hil "
            "-- gateware`, which computes the vectors" % VECTORS_ENV)
    with open(path) as f:
        return json.load(f)


def signed(value, bits):
    value &= (1 << bits) - 1
    return value - (1 << bits) if value >> (bits - 1) else value


def word_entry(word, flags):
    return word | (flags << 32)


def tile_entry(tile, node_bits):
    row_base, col_base, mirror_col_base, mirrored = tile
    return (row_base | (col_base << node_bits) | (mirror_col_base << (2 * node_bits))
            | (int(mirrored) << (3 * node_bits)))


def p_entry(lanes):
    return sum((v & MASK32) << (32 * i) for i, v in enumerate(lanes[:3]))


def shared_entry(entry):
    row, mask, owner = entry
    return row | (mask << 16) | (owner << 24)


def kp_lanes(entry):
    return [signed(entry >> (64 * i), 64) for i in range(3)]


def padded(values, depth):
    return list(values) + [0] * (depth - len(values))


def init_unit(unit, case, m):
    """Fills MVU m's word, tile and p memories with the case's program (p of its first phase)."""
    words = case["words"][m] if m < len(case["words"]) else []
    tiles = case["tiles"][m] if m < len(case["tiles"]) else []
    unit.words.memory.init = padded([word_entry(w, f) for w, f in words], unit.words_depth)
    unit.tiles.init(tile_entry(t, unit.node_bits) for t in tiles)
    p = [p_entry(lanes) for lanes in case["phases"][0]["p"]]
    unit.p_col.memory.init = padded(p, unit.nodes_depth)
    unit.p_row.memory.init = padded(p, unit.nodes_depth)
    # Kp as an earlier matrix might have left it: the first write-backs must overwrite it.
    unit.kp.memory.init = [(0x5A5A5A5A5A5A5A5A * (row + 1)) & ((1 << 192) - 1)
                           for row in range(unit.nodes_depth)]


def length(case, m):
    return case["lengths"][m] if m < len(case["lengths"]) else 0


def set_p(unit, p):
    """Simulation writes of a new p into MVU ``unit``'s copies."""
    for i, lanes in enumerate(p):
        yield unit.p_col.memory[i].eq(p_entry(lanes))
        yield unit.p_row.memory[i].eq(p_entry(lanes))
