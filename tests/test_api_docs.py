"""The public API is documented and annotated, and `make docs` has a page for it.

Public = every name in ``__all__`` of ``fastsdf`` and of each of its modules whose name has no
leading underscore, plus the public methods and properties of public classes.
"""

import importlib
import inspect
import os
import pkgutil
import re

import fastsdf

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def public_modules():
    names = ["fastsdf"] + [
        m.name
        for m in pkgutil.walk_packages(fastsdf.__path__, "fastsdf.")
        if not any(p.startswith("_") for p in m.name.split(".")[1:])
    ]
    return [importlib.import_module(n) for n in names]


def public_objects():
    """``(qualified name, object)`` for every public function, class, method and property."""
    seen = set()
    for module in public_modules():
        for name in getattr(module, "__all__", []):
            obj = getattr(module, name)
            if not (inspect.isclass(obj) or inspect.isfunction(obj)) or id(obj) in seen:
                continue
            seen.add(id(obj))
            yield f"{module.__name__}.{name}", obj
            if inspect.isclass(obj):
                for attr, member in vars(obj).items():
                    if attr.startswith("_") and attr != "__init__":
                        continue
                    if inspect.isfunction(member) or isinstance(member, property):
                        yield f"{module.__name__}.{name}.{attr}", member


def test_every_public_module_has_a_docstring_and_all():
    for module in public_modules():
        assert inspect.getdoc(module), module.__name__
        assert hasattr(module, "__all__"), module.__name__
        for name in module.__all__:
            assert hasattr(module, name), f"{module.__name__}.{name} is in __all__ but missing"


def test_every_public_name_has_a_docstring():
    missing = [
        name
        for name, obj in public_objects()
        if not name.endswith(".__init__") and not inspect.getdoc(obj)
    ]
    assert not missing, missing


def test_every_public_function_is_annotated():
    missing = []
    for name, obj in public_objects():
        fn = obj.fget if isinstance(obj, property) else obj
        if not inspect.isfunction(fn):
            continue
        sig = inspect.signature(fn)
        params = [
            p.name
            for p in sig.parameters.values()
            if p.name not in ("self", "cls")
            and p.annotation is inspect.Parameter.empty
            and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
        ]
        no_return = sig.return_annotation is inspect.Signature.empty and not name.endswith(
            ".__init__"
        )
        if params or no_return:
            missing.append(f"{name}({', '.join(params)}){' -> ?' if no_return else ''}")
    assert not missing, "\n".join(missing)


def test_package_ships_py_typed():
    assert os.path.exists(os.path.join(os.path.dirname(fastsdf.__file__), "py.typed"))
    with open(os.path.join(REPO, "setup.cfg"), encoding="utf-8") as fh:
        assert "py.typed" in fh.read()


def test_the_api_reference_documents_the_public_packages():
    """docs/api (Sphinx autodoc, built by `make docs`) covers each public package's ``__all__``:
    the packages that export names, and the public modules of those that export none."""
    documented = set()
    for name in os.listdir(os.path.join(REPO, "docs", "api")):
        if name.endswith(".rst"):
            with open(os.path.join(REPO, "docs", "api", name), encoding="utf-8") as fh:
                documented |= set(re.findall(r"^\.\. automodule:: (\S+)$", fh.read(), re.M))
    packages = ["fastsdf", "fastsdf.graph", "fastsdf.particles", "fastsdf.granular"]
    packages += ["fastsdf.fields", "fastsdf.geometry", "fastsdf.io", "fastsdf.viz"]
    for name in packages:
        module = importlib.import_module(name)
        if module.__all__:
            assert name in documented, name
            continue
        for m in pkgutil.iter_modules(module.__path__, name + "."):
            if m.name.rsplit(".", 1)[1].startswith("_"):
                continue  # private (and not imported: the CUDA kernels need numba-cuda)
            if importlib.import_module(m.name).__all__:
                assert m.name in documented, m.name
    internal = [m for m in documented if m.startswith(("fastsdf.expr", "fastsdf.backends"))]
    assert not internal, internal


def documented_parameters(doc):
    """The names of a numpy-style docstring's ``Parameters`` section, in order (a line
    ``a, b : type`` names two). The section ends at prose or the next section's title."""
    lines = doc.splitlines()
    titles = [i for i, line in enumerate(lines) if line.strip() == "Parameters"]
    if not titles:
        return []
    start = titles[0]
    assert set(lines[start + 1].strip()) == {"-"}, "a numpy section: 'Parameters' underlined"
    indent = len(lines[start]) - len(lines[start].lstrip())
    entry = re.compile(r"\s*\w+(\s*,\s*\w+)*\s*(:|$)")
    names = []
    for k in range(start + 2, len(lines)):
        line = lines[k]
        if not line.strip():
            continue
        depth = len(line) - len(line.lstrip())
        if depth > indent:
            continue  # a description
        underlined = k + 1 < len(lines) and set(lines[k + 1].strip()) == {"-"}
        if depth < indent or underlined or not entry.match(line):
            break
        names += [n.strip() for n in line.split(":")[0].split(",")]
    return names


def test_documented_parameter_parser():
    doc = "Head.\n\nParameters\n----------\na, b : int\n    Two.\nc\n    One.\n\nProse.\n"
    assert documented_parameters(doc) == ["a", "b", "c"]
    doc2 = "Parameters\n----------\nx : float\n    X.\n\nReturns\n-------\ny : float\n"
    assert documented_parameters(doc2) == ["x"]


def test_public_classes_show_their_parameters_each_documented_once():
    """``help()`` and the API pages show a class's real parameters (not ``*args, **kwargs``),
    and its docstring's Parameters section names each of them once, and nothing else."""
    from fastsdf.granular import ContactLaw, GranularSimulation
    from fastsdf.particles import (
        Drag,
        FieldForce,
        GrainSimulation,
        Gravity,
        ParticleSimulation,
    )

    for cls in (
        ParticleSimulation,
        GrainSimulation,
        GranularSimulation,
        ContactLaw,
        Gravity,
        Drag,
        FieldForce,
    ):
        params = inspect.signature(cls).parameters.values()
        variadic = [p.name for p in params if p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
        assert not variadic, (cls.__name__, variadic)
        documented = documented_parameters(inspect.getdoc(cls))
        assert len(documented) == len(set(documented)), (cls.__name__, documented)
        assert sorted(documented) == sorted(p.name for p in params), cls.__name__


# The packages whose every public call names each of its parameters in its docstring (what
# they take, in which units, which values); the others' are listed in the wave's report.
NAMED_PARAMETERS = (
    "fastsdf.function",
    "fastsdf.fields",
    "fastsdf.graph",
    "fastsdf.shapes",
    "fastsdf.geometry",
    "fastsdf.viz",
    "fastsdf.io",
    "fastsdf.apps",
    "fastsdf.notice",
    "fastsdf.introspect",
    "fastsdf.particles",
    "fastsdf.granular",
)


def test_every_public_call_names_its_parameters():
    """``help(call)`` answers what each argument is: every parameter of a public function,
    method or class (its ``__init__``'s) is named in its docstring."""
    missing = []
    for name, obj in public_objects():
        if isinstance(obj, property) or name.endswith(".__init__"):
            continue
        if not getattr(obj, "__module__", "").startswith(NAMED_PARAMETERS):
            continue
        doc = inspect.getdoc(obj) or ""
        if inspect.isclass(obj):
            doc += "\n" + (inspect.getdoc(obj.__init__) or "")
        try:
            params = inspect.signature(obj).parameters
        except (TypeError, ValueError):
            continue
        unnamed = [
            p
            for p in params
            if p not in ("self", "cls", "args", "kwargs")
            and not re.search(rf"\b{re.escape(p)}\b", doc)
        ]
        if unnamed:
            missing.append(f"{name}: {unnamed}")
    assert not missing, "\n".join(missing)


def test_signatures_show_types_not_forward_references():
    """``help()`` and ``inspect.signature`` show ``float``, not ``ForwardRef('float')`` (what a
    NamedTuple keeps under ``from __future__ import annotations``, unless its module applies
    ``fastsdf.introspect.show_field_types``)."""
    shown = []
    for name, obj in public_objects():
        if isinstance(obj, property):
            continue
        try:
            signature = str(inspect.signature(obj))
        except (TypeError, ValueError):
            continue
        if "ForwardRef" in signature:
            shown.append(f"{name}{signature}")
    assert not shown, "\n".join(shown)
