"""Generated code as objects: expressions and statements that know what they read and define.

The emitter (:mod:`fastsdf.backends.emit`) builds them; each target renders them as text once,
last: the CPU's point functions and SIMD block kernels (:mod:`fastsdf.backends.kernel`) and the
CUDA target's device functions (:mod:`fastsdf.backends.cuda`). A target chooses names (a lane's
copy of a variable), functions (the CPU's vectorisable ``exp`` or the C library's) and what a
table read or a stored subexpression becomes (a scratch row of a block, an array element).

Expressions are built with Python's operators (``a * b + c``), so an expression has the tree
Python's parser gives the same text: rendering adds parentheses only where that tree needs them,
and the generated arithmetic is the one written.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

from fastsdf.expr.ops import lit

__all__ = [
    "Code",
    "Assign",
    "Length",
    "Loop",
    "Store",
    "Stmt",
    "Statement",
    "Style",
    "var",
    "num",
    "const",
    "call",
    "lit",
    "render",
    "walk",
    "line_count",
]


_PREC = {"<": 1, "<=": 1, ">": 1, ">=": 1, "+": 2, "-": 2, "*": 3, "/": 3, "neg": 4, "**": 5}
_ATOM = 6


class Code:
    """One expression of generated code. ``op`` is ``'var'`` (``args``: name, scope: ``'p'`` a
    value per point, ``'b'`` one per call or block such as the time, ``'i'`` a loop index),
    ``'num'`` (a float), ``'const'`` (a number of the scene: see :func:`const`), ``'table'``
    (a constant table by name), ``'read'`` (table, row index,
    column), ``'fold'`` (a stored subexpression's entry: group, entry), ``'call'`` (function
    name, arguments), a binary operator (``'+'``, ``'-'``, ``'*'``, ``'/'``, ``'**'``, ``'<'``,
    ``'<='``, ``'>'``, ``'>='``) or ``'neg'``."""

    __slots__ = ("op", "args")

    def __init__(self, op: str, args: tuple) -> None:
        self.op, self.args = op, args

    # arithmetic builds trees, as Python parses the same text
    def __add__(self, o: Operand) -> Code:
        return Code("+", (self, _wrap(o)))

    def __radd__(self, o: Operand) -> Code:
        return Code("+", (_wrap(o), self))

    def __sub__(self, o: Operand) -> Code:
        return Code("-", (self, _wrap(o)))

    def __rsub__(self, o: Operand) -> Code:
        return Code("-", (_wrap(o), self))

    def __mul__(self, o: Operand) -> Code:
        return Code("*", (self, _wrap(o)))

    def __rmul__(self, o: Operand) -> Code:
        return Code("*", (_wrap(o), self))

    def __truediv__(self, o: Operand) -> Code:
        return Code("/", (self, _wrap(o)))

    def __rtruediv__(self, o: Operand) -> Code:
        return Code("/", (_wrap(o), self))

    def __pow__(self, o: Operand) -> Code:
        return Code("**", (self, _wrap(o)))

    def __neg__(self) -> Code:
        return Code("neg", (self,))

    def __lt__(self, o: Operand) -> Code:
        return Code("<", (self, _wrap(o)))

    def __le__(self, o: Operand) -> Code:
        return Code("<=", (self, _wrap(o)))

    def __gt__(self, o: Operand) -> Code:
        return Code(">", (self, _wrap(o)))

    def __ge__(self, o: Operand) -> Code:
        return Code(">=", (self, _wrap(o)))

    __hash__ = object.__hash__

    @property
    def name(self) -> str:
        """A variable's name."""
        assert self.op == "var"
        return self.args[0]

    def is_num(self, value: float | None = None) -> bool:
        """Whether this is a literal (of ``value``, compared by its text, if given)."""
        return self.op == "num" and (value is None or lit(self.args[0]) == lit(value))

    @property
    def boolean(self) -> bool:
        """Whether the value is a comparison."""
        return _PREC.get(self.op) == 1

    def __repr__(self) -> str:
        return f"Code({render(self)})"


Operand = Code | float | int


def _wrap(o: Operand) -> Code:
    return o if isinstance(o, Code) else Code("num", (float(o),))


def var(name: str, scope: str = "p") -> Code:
    """A variable: ``scope`` ``'p'`` (per point), ``'b'`` (per call), ``'i'`` (loop index)."""
    return Code("var", (name, scope))


def num(value: float) -> Code:
    """A float literal."""
    return Code("num", (float(value),))


def const(value: float) -> Code:
    """A number of the scene (a constant of its graph, a blend's ``k``): a literal in per-point
    code, read from the call's data in block kernels, so that scenes that differ only in such
    numbers share their compiled block kernels."""
    return Code("const", (float(value),))


def call(fn: str, *args: Operand) -> Code:
    """A call of ``fn`` (a name the target maps: ``'exp'``, ``'log'``, ``'log1p'``, ``'sqrt'``,
    ``'hypot'``, ``'sin'``, ``'cos'``, ``'abs'``, ``'floor'``, ``'sel'``, ``'float'``, or a
    compiled primitive ``'_P.<name>'``)."""
    return Code("call", (fn, *map(_wrap, args)))


def table(name: str) -> Code:
    """A constant table as a value (an argument of a compiled primitive)."""
    return Code("table", (name,))


def read(name: str, row: Code, col: int) -> Code:
    """Element ``[row, col]`` of a constant table."""
    return Code("read", (name, row, col))


def fold_entry(group: int, entry: int) -> Code:
    """Entry ``entry`` of the values stored by fold group ``group`` (see :class:`Store`)."""
    return Code("fold", (group, entry))


# -- statements ------------------------------------------------------------------------------


class Statement:
    """A statement of generated code: what it assigns (:meth:`defs`), what it reads
    (:meth:`reads`), and whether its value is a boolean (stored as 0.0 / 1.0 between loops)."""

    __slots__ = ()
    boolean = False

    def defs(self, vmath: bool) -> tuple:
        """The names it assigns (``vmath``: rendered with the vectorisable functions)."""
        return ()

    def reads(self) -> Iterator[Code]:
        """Every node of the expressions it reads."""
        return iter(())


class Assign(Statement):
    """``targets = value`` (one name, or several for a call returning a tuple)."""

    __slots__ = ("targets", "value")

    def __init__(self, targets: tuple, value: Code) -> None:
        self.targets, self.value = targets, value

    def defs(self, vmath: bool) -> tuple:
        return self.targets

    def reads(self) -> Iterator[Code]:
        return walk(self.value)

    @property
    def boolean(self) -> bool:  # type: ignore[override]
        """Whether the value is a comparison."""
        return self.value.boolean


class Length(Statement):
    """``r = length(a, b)`` (``sqrt(a*a + b*b)`` without overflow or underflow), and with
    ``grad`` its partials ``rp = a / r``, ``rq = b / r``. Targets render it as they choose:
    the branch-free ``_vlength`` of :mod:`fastsdf.backends.kernel.vmath`, or the plain formula
    with ``math.hypot`` where it over- or underflows."""

    __slots__ = ("r", "a", "b", "grad")

    def __init__(self, r: str, a: Code, b: Code, grad: bool) -> None:
        self.r, self.a, self.b, self.grad = r, a, b, grad

    def defs(self, vmath: bool) -> tuple:
        r = self.r
        if not self.grad:
            return (r,)
        return (r, f"{r}p", f"{r}q") if vmath else (r, f"{r}i", f"{r}p", f"{r}q")

    def reads(self) -> Iterator[Code]:
        yield from walk(self.a)
        yield from walk(self.b)


class Store(Statement):
    """Store a folded subexpression's value (``slot`` 0) or gradient component (``slot`` > 0)
    for member ``index`` of fold group ``group`` (``size`` values per member)."""

    __slots__ = ("group", "index", "size", "slot", "value")

    def __init__(self, group: int, index: Code, size: int, slot: int, value: Code) -> None:
        self.group, self.index, self.size, self.slot, self.value = group, index, size, slot, value

    def reads(self) -> Iterator[Code]:
        return walk(self.value)


class Loop(Statement):
    """A loop over the rows of a table: ``index`` (a variable of scope ``'i'``) runs over
    ``range(count)`` (a fold group), or, for a chain's loop group ``group``, over the row list
    ``_act[_off[group]:_off[group + 1]]`` (all rows, or a tile's pruned list)."""

    __slots__ = ("index", "group", "count", "body")

    def __init__(self, index: Code, body: list, group: int | None = None, count: int = 0) -> None:
        self.index, self.body, self.group, self.count = index, body, group, count

    def defs(self, vmath: bool) -> tuple:
        return tuple(n for st in self.body for n in st.defs(vmath))

    def reads(self) -> Iterator[Code]:
        for st in self.body:
            yield from st.reads()


Stmt = Statement


def walk(code: Code) -> Iterator[Code]:
    """Every node of an expression (itself first)."""
    stack = [code]
    while stack:
        c = stack.pop()
        yield c
        if c.op in ("call",):
            stack.extend(c.args[1:])
        elif c.op == "read":
            stack.append(c.args[1])
        elif c.op in _PREC:
            stack.extend(c.args)


def line_count(stmts: list, vmath: bool) -> int:
    """Lines of the rendered statements (a loop counts its header and body)."""
    n = 0
    for st in stmts:
        if isinstance(st, Loop):
            n += 1 + (st.group is not None) + line_count(st.body, vmath)
        elif isinstance(st, Length) and not vmath:
            n += 12 if st.grad else 3
        else:
            n += 1
    return n


# -- rendering -------------------------------------------------------------------------------

#: The functions of the C library (and numba's builtins) by the names the emitter calls.
MATH = {
    "exp": "math.exp",
    "log": "math.log",
    "log1p": "math.log1p",
    "sqrt": "math.sqrt",
    "hypot": "math.hypot",
    "sin": "math.sin",
    "cos": "math.cos",
    "abs": "abs",
    "floor": "np.floor",
    "sel": "_sel",
    "float": "float",
}
#: The CPU's: the vectorisable exp and log of :mod:`fastsdf.backends.kernel.vmath`.
VMATH = dict(MATH, exp="_vexp", log="_vlog", log1p="_vlog1p")


class Style:
    """How a target writes an expression: ``funcs`` maps the emitter's function names,
    ``name(var_name, scope)`` a variable's name, ``read(table, row, col)`` a table element,
    ``fold(group, entry)`` a stored subexpression (each given rendered arguments) and
    ``const(code)`` a number of the scene (a literal by default)."""

    def __init__(
        self,
        funcs: dict | None = None,
        name: Callable[[str, str], str] | None = None,
        read: Callable[[str, str, int], str] | None = None,
        fold: Callable[[int, int], str] | None = None,
        const: Callable[[Code], str] | None = None,
    ) -> None:
        self.funcs = MATH if funcs is None else funcs
        self.name = name or (lambda n, scope: n)
        self.read = read or (lambda t, row, col: f"{t}[{row}, {col}]")
        self.fold = fold or (lambda g, e: f"_F{g}[{e}]")
        self.const = const or (lambda c: lit(c.args[0]))

    @property
    def vmath(self) -> bool:
        """Whether the target uses the vectorisable functions."""
        return self.funcs["exp"] != "math.exp"


_PLAIN = Style()


def render(code: Code, style: Style = _PLAIN) -> str:
    """Python source of an expression."""
    return _render(code, style)[0]


def _render(c: Code, st: Style) -> tuple[str, int]:
    op = c.op
    if op == "var":
        return st.name(c.args[0], c.args[1]), _ATOM
    if op == "num":
        return lit(c.args[0]), _ATOM
    if op == "const":
        return st.const(c), _ATOM
    if op == "table":
        return c.args[0], _ATOM
    if op == "read":
        return st.read(c.args[0], render(c.args[1], st), c.args[2]), _ATOM
    if op == "fold":
        return st.fold(c.args[0], c.args[1]), _ATOM
    if op == "call":
        fn = c.args[0]
        name = st.funcs.get(fn, fn)
        return f"{name}({', '.join(render(a, st) for a in c.args[1:])})", _ATOM
    p = _PREC[op]
    if op == "neg":
        text, q = _render(c.args[0], st)
        return "-" + (text if q > p else f"({text})"), p
    (ta, qa), (tb, qb) = _render(c.args[0], st), _render(c.args[1], st)
    if op == "**":  # right-associative
        left, right = qa > p, qb >= p
    elif p == 1:  # comparisons never chain
        left, right = qa > p, qb > p
    else:
        left, right = qa >= p, qb > p
    return f"{ta if left else f'({ta})'} {op} {tb if right else f'({tb})'}", p


def render_stmt(stmt: Stmt, style: Style, store: Callable[[Store], str] | None = None) -> list:
    """Lines (unindented, loop bodies indented by four spaces) of one statement."""
    if isinstance(stmt, Assign):
        return [
            f"{', '.join(style.name(t, 'p') for t in stmt.targets)} = {render(stmt.value, style)}"
        ]
    if isinstance(stmt, Length):
        return _render_length(stmt, style)
    if isinstance(stmt, Store):
        assert store is not None, "a Store is rendered by the target that lays out the stores"
        return [f"{store(stmt)} = {render(stmt.value, style)}"]
    assert isinstance(stmt, Loop)
    idx = render(stmt.index, style)
    body = [line for st in stmt.body for line in render_stmt(st, style, store)]
    if stmt.group is None:
        return [f"for {idx} in range({stmt.count}):"] + ["    " + ln for ln in body]
    g = stmt.group
    head = [f"for {idx}q in range(_off[{g}], _off[{g + 1}]):", f"    {idx} = _act[{idx}q]"]
    return head + ["    " + ln for ln in body]


def _render_length(st: Length, style: Style) -> list:
    name = lambda suffix: style.name(st.r + suffix, "p")
    r, a, b = name(""), render(st.a, style), render(st.b, style)
    if style.vmath:
        if st.grad:
            return [f"{r}, {name('p')}, {name('q')} = _vlength_grad({a}, {b})"]
        return [f"{r} = _vlength({a}, {b})"]
    # sqrt(a*a + b*b) unless that over- or underflows; hypot is exact but slower. The
    # partials (a, b) / r are recomputed in the rare branch (1 / r overflows for subnormal r).
    sqrt, hypot = style.funcs["sqrt"], style.funcs["hypot"]
    lines = [f"{r} = {sqrt}({a} * {a} + {b} * {b})"]
    if not st.grad:
        return lines + [f"if not (1e-150 < {r} < 1e150):", f"    {r} = {hypot}({a}, {b})"]
    ri, rp, rq = name("i"), name("p"), name("q")
    return lines + [
        f"{ri} = 1.0 / {r}",
        f"{rp} = {a} * {ri}",
        f"{rq} = {b} * {ri}",
        f"if not (1e-150 < {r} < 1e150):",
        f"    {r} = {hypot}({a}, {b})",
        f"    {ri} = {lit(2.0**600)} if {r} < 1e-150 else 1.0",
        f"    {rp} = {a} * {ri}",
        f"    {rq} = {b} * {ri}",
        f"    {ri} = {hypot}({rp}, {rq})",
        f"    {rp} = {rp} / {ri} if {ri} > 0.0 else 1.0",
        f"    {rq} = {rq} / {ri} if {ri} > 0.0 else 0.0",
    ]


def tables_read(stmts: list) -> list:
    """The constant tables the statements read, in order of first use."""
    seen: dict[str, None] = {}
    for st in stmts:
        for c in st.reads():
            if c.op in ("table", "read"):
                seen.setdefault(c.args[0])
    return list(seen)


def any_call(stmts: list, prefix: str) -> bool:
    """Whether the statements call a function whose name starts with ``prefix``."""
    return any(c.op == "call" and c.args[0].startswith(prefix) for st in stmts for c in st.reads())
