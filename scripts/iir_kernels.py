"""Write piezo_valve_ros/core/model/_iir_kernels.py: the numba kernels of ``core/model/iir.py``, one per filter
length, written out so that every state and coefficient is a local (numba keeps them in registers; an array of
states in a loop over taps costs a memory round trip in every recursion).  ``--check``: exit 1 when the file
differs (the tests run that).

    python scripts/iir_kernels.py [--check]
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from generated_page import main_for  # noqa: E402

OUT = Path(__file__).resolve().parent.parent / "piezo_valve_ros" / "core" / "model" / "_iir_kernels.py"
TAPS = range(2, 9)     # filter lengths (the longer of b and a) with a kernel
COLUMNS_BLOCK = 64     # samples a columns kernel filters before writing them out as rows
# a subnormal output is flushed to zero, as a CPU's flush-to-zero mode does: a recursion whose input rests at zero
# decays into the subnormal range and can cycle there for ever (the last bit's rounding sustains it), and every
# operation on a subnormal costs tens of times a normal one, here and in the BLAS products of the rows filtered
# (an identification's design rows through G were 30 % subnormal on a record with holds: its solves ran 20x slower)
FLUSH_LINE = "if -TINY < y < TINY: y = 0.0"   # in the recursion itself (the first-order bank, which creep's rows match)
# the rows and columns kernels flush off the recursion's path: a subnormal output as it is stored, a subnormal state
# at the end of each block of FLUSH_BLOCK samples (at most that many samples of subnormal arithmetic where a
# recursion decays into them; a flush on the path of every sample, on each output before the states take it, made
# the recursion ~1.7x slower on one row and ~1.5x on four)
FLUSH_BLOCK = 256
STORE = "0.0 if -TINY < y < TINY else y"


def _flush_states(names: list[str]) -> list[str]:
    """Lines that set each of the states ``names`` that is subnormal to zero."""
    return [f"if -TINY < {s} < TINY: {s} = 0.0" for s in names]


def unroll(taps: int) -> int:
    """Rows advanced together: enough independent recursions to hide each one's latency, few enough that their
    states and the coefficients stay in registers."""
    return 4 if taps <= 4 else 2


def _names(prefix: str, count: int) -> str:
    return ", ".join(f"{prefix}{i}" for i in range(count))


def _step(row: str, taps: int, x: str) -> list[str]:
    """One sample of one row: lfilter's transposed direct form II, its operations in its order."""
    s = [f"s{row}_{j}" for j in range(taps - 1)]
    lines = [f"u = {x}", f"y = {s[0]} + b0 * u"]
    for j in range(taps - 2):
        lines.append(f"{s[j]} = {s[j + 1]} + u * b{j + 1} - y * a{j + 1}")
    lines.append(f"{s[taps - 2]} = u * b{taps - 1} - y * a{taps - 1}")
    lines.append(f"o{row}[n] = {STORE}")
    return lines


def _rows_kernel(taps: int) -> str:
    width = unroll(taps)
    states = taps - 1
    b_names, b_values = ", ".join(f"b{j}" for j in range(taps)), ", ".join(f"b[{j}]" for j in range(taps))
    a_names, a_values = ", ".join(f"a{j}" for j in range(1, taps)), ", ".join(f"a[{j}]" for j in range(1, taps))

    def load(rows: range, first: str) -> list[str]:
        return [f"s{r}_{j} = z[{j}, {first} + {r}]" for r in rows for j in range(states)]

    def store(rows: range, first: str) -> list[str]:
        return [f"z[{j}, {first} + {r}] = s{r}_{j}" for r in rows for j in range(states)]

    body = ["@numba.njit(nogil=True, cache=True)",
            f"def rows_{taps}(b, a, x, z, out):",
            f'    """Filters of {taps} taps on each row of x (k, N); z ({states}, k) states in and out; out (k, N)."""',
            "    k, n_samples = x.shape",
            f"    {b_names} = {b_values}",
            f"    {a_names} = {a_values}",
            "    g = 0",
            f"    while g + {width} <= k:"]
    body += [f"        {line}" for line in load(range(width), "g")]
    body += [f"        x{r}, o{r} = x[g + {r}], out[g + {r}]" for r in range(width)]
    body += [f"        for start in range(0, n_samples, {FLUSH_BLOCK}):",
             f"            for n in range(start, min(start + {FLUSH_BLOCK}, n_samples)):"]
    for r in range(width):
        body += [f"                {line}" for line in _step(str(r), taps, f"x{r}[n]")]
    body += [f"            {line}" for line in _flush_states([f"s{r}_{j}" for r in range(width) for j in range(states)])]
    body += [f"        {line}" for line in store(range(width), "g")]
    body += [f"        g += {width}",
             "    while g < k:"]
    body += [f"        {line}" for line in load(range(1), "g")]
    body += ["        x0, o0 = x[g], out[g]",
             f"        for start in range(0, n_samples, {FLUSH_BLOCK}):",
             f"            for n in range(start, min(start + {FLUSH_BLOCK}, n_samples)):"]
    body += [f"                {line}" for line in _step("0", taps, "x0[n]")]
    body += [f"            {line}" for line in _flush_states([f"s0_{j}" for j in range(states)])]
    body += [f"        {line}" for line in store(range(1), "g")]
    body += ["        g += 1"]
    return "\n".join(body) + "\n"


def _columns_kernel(taps: int) -> str:
    """The filter on each column of a sample-major x (N, k) less ``first`` (k,), written out as rows (k, N): at each
    sample every column's recursion in one loop over the columns (independent: numba runs it on vector registers),
    a block of COLUMNS_BLOCK samples kept and then written row by row."""
    states = taps - 1
    b_names, b_values = ", ".join(f"b{j}" for j in range(taps)), ", ".join(f"b[{j}]" for j in range(taps))
    a_names, a_values = ", ".join(f"a{j}" for j in range(1, taps)), ", ".join(f"a[{j}]" for j in range(1, taps))
    body = ["@numba.njit(nogil=True, cache=True)",
            f"def columns_{taps}(b, a, x, first, z, out):",
            f'    """Filters of {taps} taps on each column of x (N, k) less first (k,); z ({states}, k) states in and out; '
            'out\n    (k, N): the filtered columns as rows."""',
            "    n_samples, k = x.shape",
            f"    {b_names} = {b_values}",
            f"    {a_names} = {a_values}"]
    body += [f"    s{j} = z[{j}].copy()" for j in range(states)]
    body += [f"    block = np.empty(({COLUMNS_BLOCK}, k))",
             f"    for start in range(0, n_samples, {COLUMNS_BLOCK}):",
             f"        m = min({COLUMNS_BLOCK}, n_samples - start)",
             "        for i in range(m):",
             "            xi, yi = x[start + i], block[i]",
             "            for j in range(k):",
             "                u = xi[j] - first[j]",
             "                y = s0[j] + b0 * u"]
    for j in range(states - 1):
        body.append(f"                s{j}[j] = s{j + 1}[j] + u * b{j + 1} - y * a{j + 1}")
    body += [f"                s{states - 1}[j] = u * b{taps - 1} - y * a{taps - 1}",
             f"                yi[j] = {STORE}",
             "        for j in range(k):"]
    body += [f"            {line}" for line in _flush_states([f"s{i}[j]" for i in range(states)])]
    body += ["        for j in range(k):",
             "            oj = out[j]",
             "            for i in range(m):",
             "                oj[start + i] = block[i, j]"]
    body += [f"    z[{j}] = s{j}" for j in range(states)]
    return "\n".join(body) + "\n"


def _bank_kernel() -> str:
    width = 4
    body = ["@numba.njit(nogil=True, cache=True)",
            "def first_order_bank(x, b0, b1, a1, z, out):",
            '    """First-order filters (b0_i + b1_i z^-1) / (1 + a1_i z^-1), one per element of b0, b1, a1 (k), on '
            'one\n    input x (N,); z (k,) states in and out; out (k, N)."""',
            "    k = b0.size",
            "    g = 0",
            f"    while g + {width} <= k:"]
    for r in range(width):
        body.append(f"        c{r}, d{r}, e{r} = b0[g + {r}], b1[g + {r}], a1[g + {r}]")
        body.append(f"        p{r}, o{r} = z[g + {r}], out[g + {r}]")
    body += ["        for n in range(x.size):", "            u = x[n]"]
    for r in range(width):
        body.append(f"            y = p{r} + c{r} * u")
        body.append(f"            {FLUSH_LINE}")
        body.append(f"            p{r} = u * d{r} - y * e{r}")
        body.append(f"            o{r}[n] = y")
    body += [f"        z[g + {r}] = p{r}" for r in range(width)]
    body += [f"        g += {width}",
             "    while g < k:",
             "        c0, d0, e0, p0, o0 = b0[g], b1[g], a1[g], z[g], out[g]",
             "        for n in range(x.size):",
             "            u = x[n]",
             "            y = p0 + c0 * u",
             "            " + FLUSH_LINE,
             "            p0 = u * d0 - y * e0",
             "            o0[n] = y",
             "        z[g] = p0",
             "        g += 1"]
    return "\n".join(body) + "\n"


def page() -> str:
    head = '''"""numba kernels of ``iir`` (imported on first use).  Written by scripts/iir_kernels.py: do not edit by
hand.

Each is lfilter's transposed direct form II, operation by operation,

    y[n] = z0 + b0 x[n];  z_j = z_(j+1) + x[n] b_(j+1) - y[n] a_(j+1);  z_last = x[n] b_last - y[n] a_last,

on several rows at each sample (each output waits for the one before it; the rows' independent recursions
overlap), their states and the coefficients locals, then the rows left over one at a time; or (``columns_*``) on
every column of a sample-major array at each sample, in one loop over the columns.  No fast-math: the operations
and their order are lfilter's, so are the bits, except that a subnormal output (below TINY in magnitude) is
flushed to zero, as a CPU's flush-to-zero mode does: lfilter's recursion, its input at rest, decays into the
subnormal range and can cycle there, and arithmetic on subnormals is tens of times slower (here and in every
product of the rows filtered).  The rows and columns kernels flush an output as it is stored and a subnormal state
at the end of each block of samples (off the recursion's path: it runs on the unflushed output until then); the
first-order bank flushes each output in the recursion."""
from __future__ import annotations

import numba
import numpy as np

TINY = np.finfo(np.float64).tiny   # the smallest normal float: outputs below it in magnitude are flushed to zero


'''
    kernels = [_rows_kernel(t) for t in TAPS]
    table = "RUN_ROWS = {" + ", ".join(f"{t}: rows_{t}" for t in TAPS) + "}\n"
    columns = [_columns_kernel(t) for t in TAPS]
    columns_table = "RUN_COLUMNS = {" + ", ".join(f"{t}: columns_{t}" for t in TAPS) + "}\n"
    return (head + "\n\n".join(kernels) + "\n\n" + table + "\n\n" + "\n\n".join(columns) + "\n\n" + columns_table
            + "\n\n" + _bank_kernel())


if __name__ == "__main__":
    sys.exit(main_for(OUT, page, "iir_kernels.py", __doc__.splitlines()[0]))
