"""User-defined factors written as Python functions, differentiated by factord.

A residual is written once as an ordinary Python function of its variables and parameters::

    from factord.expressions import FactorType, norm

    # a range to a known beacon, from a 2D pose
    BeaconRange = FactorType(
        "beacon_range",
        variables=[("x", "se2")],
        parameters=[("beacon", "point2"), ("range", "scalar")],
        residual=lambda x, beacon, range: norm(beacon - x.translation()) - range,
    )
    graph.add(BeaconRange([X(1)], [np.array([1.0, 5.0]), 5.0], noiseModel.Isotropic.Sigma(1, 0.01)))

The function is called once, with symbols in place of the values: what it computes is recorded as
the expression tree a server's ``factor_types`` takes (``FactorType.definition``), then compiled by
the library into a tape and differentiated in forward mode, with its Jacobian checked against
central differences (the same compiler as a server session's, so the same definition runs in
process and on a server). No Jacobian is written by hand. Only what the expression language has
can be recorded: arithmetic, ``sin`` … ``atan2``, ``sqrt``, ``exp``, ``log``, ``pow``, ``wrap``,
``norm``, ``dot``, ``cross``, indexing, and the group operations of ``se2``, ``so3``, ``se3``
(``between``, ``compose``/``*``, ``inverse``, ``act``/``*``, ``translation``, ``rotation``,
``angle``, ``log``, ``exp_so3``, ``exp_se2``). A Python ``if`` on a symbol cannot be recorded and
raises ``TypeError``.

Kinds: variables ``se2``, ``se3``, ``point2``, ``point3``, ``snavely_camera``; parameters those
except ``snavely_camera``, plus ``scalar`` and ``("name", "vector", n)``.
"""

import json as _json
import numbers as _numbers

from . import _native

__all__ = [
    "Expr",
    "FactorType",
    "abs_",
    "acos",
    "asin",
    "atan",
    "atan2",
    "cos",
    "cross",
    "dot",
    "exp",
    "exp_se2",
    "exp_so3",
    "log",
    "norm",
    "se2",
    "se3",
    "sin",
    "sqrt",
    "squared_norm",
    "tan",
    "vector",
    "wrap",
]

_GROUPS = ("se2", "so3", "se3")
# What each declared kind is as a value of the language.
_VALUE_KIND = {
    "se2": "se2",
    "se3": "se3",
    "point2": "vector",
    "point3": "vector",
    "vector": "vector",
    "scalar": "scalar",
    "snavely_camera": "snavely_camera",
}


class Expr:
    """A value of a residual being recorded: its expression node and its kind (``scalar``,
    ``vector``, ``se2``, ``so3``, ``se3``, ``snavely_camera``)."""

    __slots__ = ("node", "kind")

    def __init__(self, node, kind):
        self.node = node
        self.kind = kind

    def __repr__(self):
        return f"Expr({self.kind}: {_json.dumps(self.node)})"

    # Arithmetic (scalars and vectors).
    def __add__(self, other):
        return _arith("add", self, other)

    def __radd__(self, other):
        return _arith("add", other, self)

    def __sub__(self, other):
        return _arith("sub", self, other)

    def __rsub__(self, other):
        return _arith("sub", other, self)

    def __mul__(self, other):
        """``a * b``: compose for two group elements, act for a group element and a vector (as
        GTSAM's ``Pose2 * Pose2`` and ``transformFrom``), multiplication otherwise."""
        other = _lift(other)
        if self.kind in _GROUPS and other.kind in _GROUPS:
            return self.compose(other)
        if self.kind in _GROUPS:
            return self.act(other)
        return _arith("mul", self, other)

    def __rmul__(self, other):
        return _arith("mul", other, self)

    def __truediv__(self, other):
        return _arith("div", self, other)

    def __rtruediv__(self, other):
        return _arith("div", other, self)

    def __neg__(self):
        return _op("neg", self.kind, self)

    def __pos__(self):
        return self

    def __pow__(self, other):
        return _op("pow", "scalar", self, other)

    def __rpow__(self, other):
        return _op("pow", "scalar", other, self)

    def __abs__(self):
        return _op("abs", "scalar", self)

    def __getitem__(self, index):
        """``v[i]`` is one element; ``v[i:j]`` the vector of those elements."""
        if isinstance(index, slice):
            if index.stop is None:
                raise TypeError("a slice of a recorded vector needs an end: v[0:2]")
            return vector(*(self[i] for i in range(*index.indices(index.stop))))
        if not isinstance(index, int) or index < 0:
            raise TypeError(f"a recorded vector is indexed by a non-negative int, got {index!r}")
        return _op("at", "scalar", self, _Literal(index))

    def __iter__(self):
        raise TypeError("a recorded vector cannot be iterated (its length is the compiler's); index it")

    def __bool__(self):
        raise TypeError(
            "a recorded value has no truth value: a Python `if` on it cannot be recorded "
            "(write the residual without branching on values)"
        )

    def _compared(self, other):
        raise TypeError(
            "a recorded value cannot be compared: the comparison would be made once, when the "
            "residual is recorded, not at each evaluation (write it without branching on values)"
        )

    __lt__ = __le__ = __gt__ = __ge__ = _compared

    # Group operations.
    def between(self, other):
        """``self⁻¹ · other``."""
        return _op("between", self.kind, self, other)

    def compose(self, other):
        return _op("compose", self.kind, self, other)

    def inverse(self):
        return _op("inverse", self.kind, self)

    def act(self, point):
        """``R p + t`` (GTSAM: ``transformFrom``)."""
        return _op("act", "vector", self, point)

    transformFrom = act

    def translation(self):
        return _op("translation", "vector", self)

    def rotation(self):
        return _op("rotation", "so3", self)

    def angle(self):
        """An ``se2``'s angle (not wrapped)."""
        return _op("angle", "scalar", self)

    def intrinsics(self):
        """A camera's ``[f, k1, k2]``."""
        return _op("intrinsics", "vector", self)

    def log(self):
        """``so3`` → rotation vector; ``se2`` → ``[V⁻¹ t, θ]``; a scalar's natural log."""
        return log(self)

    Logmap = log

    def norm(self):
        return norm(self)

    def dot(self, other):
        return dot(self, other)

    def cross(self, other):
        return cross(self, other)


class _Literal:
    """An integer literal (the index of ``at``), written as a bare number."""

    def __init__(self, value):
        self.value = value


def _node(value):
    if isinstance(value, _Literal):
        return value.value
    return _lift(value).node


def _lift(value):
    """A Python value as an expression: numbers are constants, sequences vectors."""
    if isinstance(value, Expr):
        return value
    if isinstance(value, bool):
        raise TypeError("a bool is not a number of a residual")
    if isinstance(value, _numbers.Real):
        number = float(value)
        if number != number or number in (float("inf"), float("-inf")):
            raise ValueError(f"a residual's constant must be finite, got {value}")
        return Expr(number, "scalar")
    try:
        items = list(value)
    except TypeError:
        raise TypeError(
            f"cannot use a {type(value).__name__} in a residual (numbers, sequences of numbers "
            "and recorded values can be)"
        ) from None
    return vector(*items)


def _op(name, kind, *args):
    return Expr({name: [_node(a) for a in args]}, kind)


def _arith(name, a, b):
    a, b = _lift(a), _lift(b)
    kind = "vector" if "vector" in (a.kind, b.kind) else "scalar"
    return _op(name, kind, a, b)


def vector(*items):
    """A vector of scalars and vectors, concatenated."""
    return Expr([_node(i) for i in items], "vector")


def _unary(name, kind="scalar"):
    def apply(x):
        return _op(name, kind, x)

    apply.__name__ = name
    apply.__doc__ = f"``{name}`` of the expression language."
    return apply


sin = _unary("sin")
cos = _unary("cos")
tan = _unary("tan")
asin = _unary("asin")
acos = _unary("acos")
atan = _unary("atan")
sqrt = _unary("sqrt")
exp = _unary("exp")
abs_ = _unary("abs")
wrap = _unary("wrap")
norm = _unary("norm")
squared_norm = _unary("squared_norm")
exp_so3 = _unary("exp_so3", "so3")
exp_se2 = _unary("exp_se2", "se2")


def log(x):
    """Natural log of a scalar; ``so3``/``se2`` logarithm (a vector)."""
    x = _lift(x)
    return _op("log", "scalar" if x.kind == "scalar" else "vector", x)


def atan2(y, x):
    return _op("atan2", "scalar", y, x)


def dot(a, b):
    return _op("dot", "scalar", a, b)


def cross(a, b):
    return _op("cross", "vector", a, b)


def se2(x, y, theta):
    return _op("se2", "se2", x, y, theta)


def se3(rotation, translation):
    return _op("se3", "se3", rotation, translation)


def _declared(item, what):
    """``("name", "kind")``, ``("name", "vector", n)`` or the wire's dict, as the wire's dict."""
    if isinstance(item, dict):
        return dict(item)
    if isinstance(item, (tuple, list)) and len(item) in (2, 3):
        declared = {"name": item[0], "kind": item[1]}
        if len(item) == 3:
            declared["len"] = item[2]
        return declared
    raise TypeError(f"{what}: expected (name, kind), (name, 'vector', length) or a dict, got {item!r}")


def _symbol(declared):
    kind = _VALUE_KIND.get(declared["kind"])
    if kind is None:
        raise ValueError(f"{declared['name']}: unknown kind {declared['kind']!r}")
    return Expr(declared["name"], kind)


class FactorType:
    """A factor type: ``FactorType(name, variables, parameters, residual)`` where ``residual`` is
    a Python function of the variables then the parameters (recorded, see the module's text) or
    an expression tree as the wire writes it. Calling the type builds a factor:
    ``factor_type(keys, parameters, noise)``."""

    def __init__(self, name, variables, parameters=(), residual=None, *, description=None):
        variables = [_declared(v, "variables") for v in variables]
        parameters = [_declared(p, "parameters") for p in parameters]
        if callable(residual):
            recorded = residual(*(_symbol(d) for d in variables + parameters))
            tree = _lift(recorded).node
        elif residual is not None:
            tree = residual
        else:
            raise TypeError("FactorType: a residual (a function or an expression tree) is needed")
        definition = {"name": name, "variables": variables, "parameters": parameters, "residual": tree}
        if description is not None:
            definition["description"] = description
        self._compile(definition)

    @classmethod
    def from_definition(cls, definition):
        """A type from the wire's definition (a dict, or its JSON text), exactly as a server's
        ``factor_types`` takes it."""
        self = cls.__new__(cls)
        self._compile(_json.loads(definition) if isinstance(definition, str) else definition)
        return self

    def _compile(self, definition):
        self._native = _native.FactorType(_json.dumps(definition))
        self.definition = _json.loads(self._native.definition_json())

    @property
    def name(self):
        return self._native.name

    @property
    def residual_dim(self):
        return self._native.residual_dim

    def __call__(self, keys, parameters, noise):
        """A factor on ``keys`` (in the order of ``variables``) measuring ``parameters`` (one
        value per declared parameter: ``Pose2``, ``Pose3``, numpy arrays, floats)."""
        if isinstance(keys, int):
            keys = [keys]
        return self._native.factor(list(keys), list(parameters), noise)

    def __repr__(self):
        return repr(self._native)
