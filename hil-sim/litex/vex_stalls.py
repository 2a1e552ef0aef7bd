#!/usr/bin/env python3
"""Why the VexRiscv did not retire: a cycle-by-cycle attribution of a Verilator trace (issue 19).

Reads the VCD that a traced SoC (deform_soc_trace.py) writes: the signals of its pipeline probe
(deform_trace_probe.v), one sample a clock. Every clock either retires an instruction in
writeBack or does not, and then the reason is one of:

- ``dcache miss``: a load missed the data cache. The VexRiscv then halts writeBack on it for two
  clocks, flushes the pipeline ("redo"), fetches from the load again and holds it in execute
  until the line is refilled: every clock of that, the flushed and refetched bubbles included;
- ``dcache store``: writeBack holds a store waiting for the write-through bus;
- a bubble in writeBack, which was made in an earlier stage and carried down the pipeline; its
  cause is the reason the stage that made it could not pass an instruction on:
  - decode held by the hazard plugin: ``load-use``, ``mul-use``, ``shift-use`` (or ``other-use``)
    by the unbypassable result's instruction, with ``@E`` when that instruction was in execute
    (the next instruction) and ``@M`` when it was in memory (one between);
  - decode empty: ``icache miss`` while the instruction bus refills a line, ``branch`` for the
    fetch restart after a jump (up to 4 clocks after one; a backward branch is predicted taken
    in decode, which costs one such clock), ``fetch`` otherwise;
  - decode or execute flushed by a jump resolved in memory (a mispredicted branch): ``branch
    flush``;
  - execute halted by the data cache (``dcache (execute)``: its flush or halt; a refill in
    progress counts as ``dcache miss``), or by a CSR: ``csr``; memory halted by the iterative
    divider: ``div``.

Every non-retiring clock is charged to the instruction that retires next (the one that waited),
so the per-instruction table shows where the stalls land. Loops are found from the retired
stream (a taken backward branch); a loop's figures are per iteration.

    vex_stalls.py locate --elf FW [--pattern NAME]   # the loop head's address, in hex
    vex_stalls.py analyse --elf FW --vcd sim.vcd [--loops 3] [--listing]
    vex_stalls.py span --elf FW --vcd sim.vcd --edge PC [--after N] [--mark PC ...]

``span`` measures a stretch of straight-line work, such as a phase between two readings of the
cycle counter: from the window's first retirement of ``--edge`` to its N-th next one (the
next by default), split at each
``--mark``'s first retirement in between, with the causes of each part's clocks and the clocks
and instructions of each function (every clock charged as in ``analyse``).

Python 3 alone, and riscv64-unknown-elf-objdump for the disassembly.
"""

import argparse
import bisect
import collections
import re
import subprocess
import sys

OBJDUMP = "riscv64-unknown-elf-objdump"

# Mnemonic sequences of the kernel loops (target-core/src/kernel/riscv.rs), to find their heads.
PATTERNS = {
    # split_mirrored_row::<1>: one direction, mirrored half, split sums (19 instructions).
    "split-mirrored-1": "lw addi srli slli and srai sub add lw lw mul mulh mul mulh add add add add bltu",
}

IMMEDIATE_FORMS = {"add", "and", "or", "xor", "sll", "srl", "sra"}

PROBE = "deform_trace_probe"
SIGNALS = [
    "clk", "wb_valid", "wb_fire", "wb_stuck", "wb_pc", "mem_valid", "mem_stuck", "mem_halt",
    "mem_remove", "mem_instr", "ex_valid", "ex_stuck", "ex_halt", "ex_hbo", "ex_remove",
    "ex_dcache", "ex_instr", "dec_valid", "dec_stuck", "dec_halt", "dec_hbo", "dec_remove",
    "hazard", "haz_ex", "haz_mem", "csr_block", "jump_dec", "jump_mem", "ibus_cyc",
]

# The order of the causes in the tables.
CAUSES = [
    "retiring", "load-use@E", "load-use@M", "mul-use@E", "mul-use@M", "shift-use@E",
    "shift-use@M", "other-use@E", "other-use@M", "branch", "branch flush", "icache miss", "fetch",
    "dcache miss", "dcache store", "dcache (execute)", "csr", "div", "decode other",
    "execute other", "window start",
]

# The causes summed into the columns (the rest: "other").
GROUPS = {
    "retiring": ["retiring"],
    "load-use": ["load-use@E", "load-use@M"],
    "mul-use": ["mul-use@E", "mul-use@M"],
    "shift-use": ["shift-use@E", "shift-use@M"],
    "branch": ["branch", "branch flush"],
    "dcache/bus": ["dcache miss", "dcache store", "dcache (execute)"],
    "icache": ["icache miss"],
}


def disassemble(elf):
    """{address: (mnemonic, operands)} of the ELF's code."""
    out = subprocess.run(
        [OBJDUMP, "-d", "--no-show-raw-insn", elf], check=True, capture_output=True, text=True
    ).stdout
    code = {}
    line = re.compile(r"^\s*([0-9a-f]+):\s+(\S+)\s*(.*)$")
    for text in out.splitlines():
        m = line.match(text)
        if m:
            mnemonic = m.group(2)
            if mnemonic.startswith("c."):
                mnemonic = mnemonic[2:]
            operands = m.group(3).split("#")[0].split("<")[0].strip()
            # objdump names a compressed immediate form by its register form (`c.addi` as
            # `add s0,s0,24`, `c.srli` as `srl`): name it as the assembler source does.
            last = operands.rsplit(",", 1)[-1]
            if mnemonic in IMMEDIATE_FORMS and re.match(r"^-?(0x[0-9a-f]+|[0-9]+)$", last.strip()):
                mnemonic += "i"
            code[int(m.group(1), 16)] = (mnemonic, operands)
    return code


def locate(code, pattern):
    """Addresses where the mnemonic sequence `pattern` starts."""
    want = pattern.split()
    addresses = sorted(code)
    names = [code[a][0] for a in addresses]
    return [
        addresses[i]
        for i in range(len(names) - len(want) + 1)
        if names[i : i + len(want)] == want
    ]


def kind(instruction):
    """load, mul, div, shift or other, from a (decompressed) 32-bit instruction."""
    opcode = instruction & 0x7F
    funct3 = (instruction >> 12) & 7
    funct7 = instruction >> 25
    if opcode == 0x03:
        return "load"
    if opcode == 0x33 and funct7 == 1:
        return "mul" if funct3 < 4 else "div"
    if opcode in (0x33, 0x13) and funct3 in (1, 5):
        return "shift"
    return "other"


def read_vcd(path):
    """The probe's signals at every rising clock edge: a list of dicts of ints."""
    ids = {}
    scope = []
    values = {}
    samples = []
    with open(path) as f:
        in_header = True
        time_changes = False
        for line in f:
            if in_header:
                words = line.split()
                if not words:
                    continue
                if words[0] == "$scope":
                    scope.append(words[2])
                elif words[0] == "$upscope":
                    scope.pop()
                elif words[0] == "$var" and scope and PROBE in scope[-1]:
                    name = words[4]
                    if name in SIGNALS:
                        ids.setdefault(words[3], []).append(name)
                elif words[0] == "$enddefinitions":
                    in_header = False
                    missing = set(SIGNALS) - {n for names in ids.values() for n in names}
                    if missing:
                        raise SystemExit(f"{path}: no probe signal {sorted(missing)}")
                continue
            c = line[0]
            if c == "#":
                if time_changes and values.get("clk") == 1:
                    samples.append(dict(values))
                time_changes = True
                continue
            if c == "b":
                value, ident = line[1:].split()
                value = int(value.replace("x", "0").replace("z", "0"), 2)
            elif c in "01xz":
                value, ident = (1 if c == "1" else 0), line[1:].strip()
            else:
                continue
            for name in ids.get(ident, ()):
                values[name] = value
        if time_changes and values.get("clk") == 1:
            samples.append(dict(values))
    return samples


def stall_cause(stage, s):
    """Why `stage` (D, E or M), valid, passes nothing on this clock (its next stage is free)."""
    if stage == "D":
        if s["hazard"]:
            producer = s["ex_instr"] if s["haz_ex"] else s["mem_instr"]
            return f"{kind(producer).replace('div', 'mul')}-use@{'E' if s['haz_ex'] else 'M'}"
        if s["dec_halt"]:
            return "dcache (execute)"
        if s["csr_block"]:
            return "csr"
        return "decode other"
    if stage == "E":
        if s["ex_dcache"]:
            return "dcache (execute)"
        if s["ex_hbo"]:
            return "dcache miss"
        if s["ex_halt"]:
            return "csr"
        return "execute other"
    return "div" if s["mem_halt"] else "execute other"


def is_store(code, pc):
    return code.get(pc, ("?",))[0] in ("sw", "sh", "sb", "swsp")


def attribute(samples, code):
    """[(cause, retired pc or None)] per clock: each non-retiring clock's cause."""
    tag = {"E": "window start", "M": "window start", "W": "window start"}
    since_jump = since_redo = 99
    clocks = []
    for s in samples:
        since_jump = 0 if (s["jump_dec"] or s["jump_mem"]) else since_jump + 1
        # A data-cache redo: writeBack's load, halted, flushes the stages behind it.
        redo = (
            s["wb_valid"] and not s["wb_fire"]
            and (s["mem_remove"] or s["ex_remove"] or s["dec_remove"])
        )
        since_redo = 0 if redo else since_redo + 1
        flushed = "dcache miss" if redo else "branch flush"
        if s["wb_fire"]:
            clocks.append(("retiring", s["wb_pc"]))
        elif s["wb_valid"]:
            store = s["wb_stuck"] and is_store(code, s["wb_pc"])
            clocks.append(("dcache store" if store else "dcache miss", None))
        else:
            clocks.append((tag["W"], None))

        def passed(stage, valid, stuck, remove):
            if not valid:
                if stage == "D":
                    if s["ibus_cyc"]:
                        return "icache miss"
                    if since_redo <= 4:
                        return "dcache miss"
                    return "branch" if since_jump <= 4 else "fetch"
                return tag[stage]
            if remove:
                return flushed
            if stuck:
                return stall_cause(stage, s)
            return None

        # A stuck stage keeps its instruction, unless a flush removes it: then its bubble's
        # cause is the flush's.
        new = {x: (flushed if redo else tag[x]) for x in tag}
        if not s["wb_stuck"]:
            new["W"] = passed("M", s["mem_valid"], s["mem_stuck"], s["mem_remove"])
        if not s["mem_stuck"]:
            new["M"] = passed("E", s["ex_valid"], s["ex_stuck"], s["ex_remove"])
        if not s["ex_stuck"]:
            new["E"] = passed("D", s["dec_valid"], s["dec_stuck"], s["dec_remove"])
        tag = new
    return clocks


def per_instruction(clocks):
    """{pc: Counter(cause)}: each clock charged to the instruction that retires next."""
    table = collections.defaultdict(collections.Counter)
    pending = collections.Counter()
    for cause, pc in clocks:
        if pc is None:
            pending[cause] += 1
            continue
        table[pc]["retiring"] += 1
        table[pc].update(pending)
        pending.clear()
    return table, pending


def find_loops(clocks, code):
    """{(head, branch): taken count}: taken backward branches of the retired stream."""
    loops = collections.Counter()
    last = None
    for cause, pc in clocks:
        if pc is None:
            continue
        if last is not None and pc < last and code.get(last, ("",))[0].startswith("b"):
            loops[(pc, last)] += 1
        last = pc
    return loops


def row(label, counter, divide, causes, width=12):
    total = sum(counter.values())
    cells = [f"{counter.get(c, 0) / divide:>{width}.2f}" for c in causes]
    return f"{label:<28} {total / divide:>9.2f}  " + " ".join(cells)


def grouped(counter):
    """`counter` summed into GROUPS' columns, the rest as "other"."""
    out = collections.Counter()
    for cause, clocks in counter.items():
        group = next((g for g, members in GROUPS.items() if cause in members), "other")
        out[group] += clocks
    return out


def header(causes, width=12):
    return f"{'':<28} {'clocks':>9}  " + " ".join(f"{c:>{width}}" for c in causes)


def report(table, pending, clocks, code, loops, listing):
    window = collections.Counter(cause for cause, _ in clocks)
    retired = window["retiring"]
    print(f"window: {len(clocks)} clocks, {retired} retired (CPI {len(clocks) / max(retired, 1):.3f})")
    shown = [c for c in CAUSES if window.get(c, 0)]
    groups = list(GROUPS) + ["other"]
    print(header(shown))
    print(row("window, total", window, 1, shown).replace(".00", "   "))
    hot = sorted(loops.items(), key=lambda item: -sum(
        sum(table[pc].values()) for pc in table if item[0][0] <= pc <= item[0][1]
    ))
    for (head, branch), taken in hot[: listing[0]]:
        inside = collections.Counter()
        for pc, counter in table.items():
            if head <= pc <= branch:
                inside.update(counter)
        iterations = table[branch]["retiring"]
        label = f"loop {head:#x}..{branch:#x}"
        print(f"{label}: {iterations} iterations ({taken} taken), per iteration:")
        print(header(shown))
        print(row("  in the loop", inside, max(iterations, 1), shown))
        print(row("  whole window", window, max(iterations, 1), shown))
        print(header(groups))
        print(row("  in the loop", grouped(inside), max(iterations, 1), groups))
        print(row("  whole window", grouped(window), max(iterations, 1), groups))
        if listing[1]:
            for pc in sorted(p for p in table if head <= p <= branch):
                mnemonic, operands = code.get(pc, ("?", ""))
                counter = table[pc]
                extra = ", ".join(
                    f"{c} {counter[c] / max(iterations, 1):.2f}" for c in CAUSES
                    if c != "retiring" and counter.get(c)
                )
                print(f"    {pc:08x}  {mnemonic:<6} {operands:<22} {sum(counter.values()) / max(iterations, 1):6.2f}  {extra}")
    if pending:
        print(f"(after the last retirement: {dict(pending)})")


def symbols(elf):
    """[(address, name)] of the ELF's functions, sorted."""
    out = subprocess.run(
        [OBJDUMP.replace("objdump", "nm"), "-C", "-n", elf], check=True, capture_output=True,
        text=True,
    ).stdout
    found = []
    for text in out.splitlines():
        fields = text.split(" ", 2)
        if len(fields) == 3 and fields[1] in "tTW":
            found.append((int(fields[0], 16), fields[2]))
    return found


def span(clocks, elf, edge, after, marks):
    """Prints the clocks from `edge`'s first retirement to its `after`-th next, split at
    `marks`."""
    retired = [(i, pc) for i, (_, pc) in enumerate(clocks) if pc is not None]
    edges = [i for i, pc in retired if pc == edge]
    if len(edges) <= after:
        sys.exit(f"{edge:#x} retires {len(edges)} time(s) in the window: no span")
    first, last = edges[0], edges[after]
    cuts = [first]
    for mark in marks:
        cuts += [next((i for i, pc in retired if pc == mark and cuts[-1] < i < last), cuts[-1])]
    cuts.append(last)
    print(f"span {edge:#x} to {edge:#x}: {last - first} clocks")
    names = ["edge"] + [f"{m:#x}" for m in marks] + ["edge"]
    for k in range(len(cuts) - 1):
        part = collections.Counter(cause for cause, _ in clocks[cuts[k] + 1 : cuts[k + 1] + 1])
        causes = ", ".join(f"{c} {n}" for c, n in part.most_common())
        print(f"  {names[k]} to {names[k + 1]}: {cuts[k + 1] - cuts[k]} clocks ({causes})")
    table = symbols(elf)
    starts = [a for a, _ in table]
    per_function = collections.defaultdict(collections.Counter)
    pending = 0
    for cause, pc in clocks[first + 1 : last + 1]:
        if pc is None:
            pending += 1
            continue
        name = table[max(bisect.bisect_right(starts, pc) - 1, 0)][1]
        per_function[name]["clocks"] += pending + 1
        per_function[name]["instructions"] += 1
        pending = 0
    for name, c in sorted(per_function.items(), key=lambda item: -item[1]["clocks"]):
        print(f"  {c['clocks']:>6} clocks {c['instructions']:>5} instructions  {name[:100]}")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    find = sub.add_parser("locate", help="print the address of a kernel loop's head")
    find.add_argument("--elf", required=True)
    find.add_argument("--pattern", default="split-mirrored-1", choices=sorted(PATTERNS))
    analyse = sub.add_parser("analyse", help="attribute a trace's clocks")
    analyse.add_argument("--elf", required=True)
    analyse.add_argument("--vcd", required=True)
    analyse.add_argument("--loops", type=int, default=3, help="hottest loops to show")
    analyse.add_argument("--listing", action="store_true", help="per-instruction cycles in the loops")
    measure = sub.add_parser("span", help="the clocks between two retirements of an instruction")
    measure.add_argument("--elf", required=True)
    measure.add_argument("--vcd", required=True)
    measure.add_argument("--edge", required=True, type=lambda t: int(t, 16))
    measure.add_argument("--after", type=int, default=1, help="end at the N-th next retirement")
    measure.add_argument("--mark", action="append", default=[], type=lambda t: int(t, 16))
    args = parser.parse_args()
    code = disassemble(args.elf)
    if args.command == "locate":
        found = locate(code, PATTERNS[args.pattern])
        if not found:
            sys.exit(f"{args.pattern}: not in {args.elf}")
        # The kernel inlines a loop into each of its tile shapes (row sums stored or added):
        # the first copy's head, the others named on stderr.
        if len(found) > 1:
            print(f"{args.pattern}: also at {[hex(a) for a in found[1:]]}", file=sys.stderr)
        print(f"{found[0]:#x}")
        return
    samples = read_vcd(args.vcd)
    if not samples:
        sys.exit(f"{args.vcd}: no clock in the trace (did the window's start pc ever retire?)")
    clocks = attribute(samples, code)
    if args.command == "span":
        span(clocks, args.elf, args.edge, args.after, args.mark)
        return
    table, pending = per_instruction(clocks)
    report(table, pending, clocks, code, find_loops(clocks, code), (args.loops, args.listing))


if __name__ == "__main__":
    main()
