"""docs/api_python.md is the package's API: every public name has a heading there, each heading's
signature is the code's (argument names, kinds and defaults), every public method has a heading
with its signature, and every public property and instance attribute is named in its class's
section. Failures list everything missing or wrong at once.

Headings name what they document in code spans: `mll.env(address=None, ...)` (a function or a
class, with its signature), `VectorEnv.step(actions)` (a method), `VectorEnv.transport` (a
property or attribute), `mll.OUTCOMES` (a constant: its section shows its value as a code span).
"""

from __future__ import annotations

import ast
import inspect
import pathlib
import re

import pytest

import multi_lunar_lander as mll
from multi_lunar_lander import sb3

_DOC = pathlib.Path(__file__).resolve().parents[2] / "docs" / "api_python.md"
_HEADING = re.compile(r"^(#{2,4}) `(?:mll\.)?([A-Za-z_][\w.]*)(?:\((.*)\))?`[ \t]*$", re.MULTILINE)
# Names outside mll's namespace that the document describes.
_EXTRA = {"SB3VecEnv": sb3.SB3VecEnv}


class Heading:
    def __init__(self, level: int, name: str, params: str | None, section: str):
        self.level, self.name, self.params, self.section = level, name, params, section


def _headings() -> list[Heading]:
    text = _DOC.read_text(encoding="utf-8")
    found = list(_HEADING.finditer(text))
    headings = []
    for match in found:
        level = len(match.group(1))
        # The section runs to the next heading of the same or a higher level.
        end = len(text)
        nxt = re.compile(rf"^#{{1,{level}}} ", re.MULTILINE).search(text, match.end())
        if nxt:
            end = nxt.start()
        headings.append(Heading(level, match.group(2), match.group(3), text[match.end():end]))
    return headings


_ALL = _headings()


def _public_objects() -> dict[str, object]:
    names = {name: getattr(mll, name) for name in mll.__all__}
    names.update(_EXTRA)
    return names


def _resolve(name: str):
    head, _, rest = name.partition(".")
    obj = _public_objects().get(head)
    if obj is None:
        return None
    for part in rest.split(".") if rest else ():
        obj = inspect.getattr_static(obj, part, None)
        if obj is None:
            return None
    return obj


def _documented_signature(params: str) -> list[tuple[str, str, object]]:
    """(name, kind, default or inspect.Parameter.empty) of `params` as written in a heading."""
    tree = ast.parse(f"def f({params}): pass").body[0].args
    found = []
    positional = tree.posonlyargs + tree.args
    defaults = [inspect.Parameter.empty] * (len(positional) - len(tree.defaults)) + [
        ast.literal_eval(d) for d in tree.defaults
    ]
    for arg, default in zip(positional, defaults):
        found.append((arg.arg, "POSITIONAL_OR_KEYWORD", default))
    if tree.vararg:
        found.append((tree.vararg.arg, "VAR_POSITIONAL", inspect.Parameter.empty))
    for arg, default in zip(tree.kwonlyargs, tree.kw_defaults):
        found.append(
            (arg.arg, "KEYWORD_ONLY", inspect.Parameter.empty if default is None else ast.literal_eval(default))
        )
    if tree.kwarg:
        found.append((tree.kwarg.arg, "VAR_KEYWORD", inspect.Parameter.empty))
    return found


def _code_signature(obj) -> list[tuple[str, str, object]]:
    function = obj.__init__ if inspect.isclass(obj) else obj
    if isinstance(function, (classmethod, staticmethod)):
        function = function.__func__
    parameters = list(inspect.signature(function).parameters.values())
    if parameters and parameters[0].name in ("self", "cls"):
        parameters = parameters[1:]
    return [(p.name, p.kind.name, p.default) for p in parameters]


def test_every_public_name_has_a_heading():
    documented = {heading.name for heading in _ALL}
    missing = sorted(name for name in _public_objects() if name not in documented)
    assert not missing, f"docs/api_python.md has no heading for {missing}"


def test_every_heading_names_something_public():
    unknown = sorted({heading.name for heading in _ALL if _resolve(heading.name) is None})
    assert not unknown, f"docs/api_python.md documents names the package does not have: {unknown}"


def test_signatures_are_the_codes():
    wrong = []
    for heading in _ALL:
        obj = _resolve(heading.name)
        if obj is None:
            continue
        callable_ = inspect.isclass(obj) or inspect.isfunction(obj) or isinstance(obj, (classmethod, staticmethod))
        if heading.params is None:
            if callable_ and not isinstance(obj, property):
                wrong.append(f"{heading.name}: a function or class; its heading must show its arguments")
            continue
        if not callable_:
            wrong.append(f"{heading.name}: not callable, but its heading shows arguments")
            continue
        documented, code = _documented_signature(heading.params), _code_signature(obj)
        if documented != code:
            wrong.append(f"{heading.name}: documented ({heading.params}), code {inspect.signature(obj)}")
    assert not wrong, "signatures in docs/api_python.md differ from the code:\n" + "\n".join(wrong)


def _own_members(cls) -> dict[str, object]:
    """Public members defined by the package's classes in `cls`'s MRO (not PettingZoo's,
    Gymnasium's or SB3's), name -> the object found first."""
    members = {}
    for klass in cls.__mro__:
        if not klass.__module__.startswith("multi_lunar_lander"):
            continue
        for name, value in vars(klass).items():
            if not name.startswith("_") and name not in members:
                members[name] = value
    return members


def _classes() -> dict[str, type]:
    return {name: obj for name, obj in _public_objects().items() if inspect.isclass(obj)}


def _section_of(name: str) -> str:
    """The text of the class's heading section and of the headings of its members."""
    parts = [h.section for h in _ALL if h.name == name or h.name.startswith(name + ".")]
    return "\n".join(parts)


def _mentioned(member: str, text: str) -> bool:
    return re.search(rf"`(?:[\w.]*\.)?{re.escape(member)}\b", text) is not None


def test_every_public_method_has_a_heading_with_its_signature():
    """A method shared by two classes (a common base) may be headed under either."""
    missing = []
    for class_name, cls in _classes().items():
        for member, value in _own_members(cls).items():
            function = value.__func__ if isinstance(value, (classmethod, staticmethod)) else value
            if not inspect.isfunction(function):
                continue
            headed = any(
                h.params is not None
                and h.name.rpartition(".")[2] == member
                and inspect.getattr_static(_resolve(h.name.rpartition(".")[0]) or object, member, None) is value
                for h in _ALL
                if "." in h.name
            )
            if not headed and not _mentioned(member, _section_of(class_name)):
                missing.append(f"{class_name}.{member}")
            elif not headed:
                missing.append(f"{class_name}.{member} (mentioned, but no heading with its signature)")
    assert not missing, f"public methods without a heading in docs/api_python.md: {missing}"


def test_every_property_and_class_attribute_is_named_in_its_section():
    missing = []
    for class_name, cls in _classes().items():
        section = _section_of(class_name)
        for member, value in _own_members(cls).items():
            if inspect.isfunction(value) or isinstance(value, (classmethod, staticmethod)):
                continue
            if not _mentioned(member, section):
                missing.append(f"{class_name}.{member}")
    assert not missing, f"properties and attributes not named in their class's section: {missing}"


@pytest.fixture(scope="module")
def instances(address):
    """One object of each class that has instance attributes."""
    made = {
        "MultiLunarLanderEnv": mll.env(address=address),
        "MultiLunarLanderParallelEnv": mll.parallel_env(address=address),
        "VectorEnv": mll.vector_env(2, address=address),
        "GymVectorEnv": mll.gym_vector_env(2, address=address),
        "SB3VecEnv": mll.sb3_vec_env(2, address=address),
        "MLLError": mll.MLLError(__import__("grpc").StatusCode.INTERNAL, "message"),
    }
    server = mll.ServerProcess(threads=1)
    made["ServerProcess"] = server
    yield made
    for obj in made.values():
        if hasattr(obj, "close"):
            obj.close()
    server.stop()


def test_every_instance_attribute_is_named_in_its_section(instances):
    missing = []
    for class_name, obj in instances.items():
        section = _section_of(class_name)
        for member in vars(obj):
            if not member.startswith("_") and not _mentioned(member, section):
                missing.append(f"{class_name}.{member}")
    assert not missing, f"instance attributes not named in their class's section: {missing}"


def test_constants_show_their_values():
    wrong = []
    for name, value in _public_objects().items():
        if callable(value):
            continue
        sections = [h.section for h in _ALL if h.name == name]
        if not sections or f"`{value!r}`" not in " ".join(sections[0].split()):
            wrong.append(f"{name} = {value!r}")
    assert not wrong, f"docs/api_python.md does not show these values as code spans: {wrong}"


def test_metadata_shown_is_the_classes(instances):
    text = " ".join(_DOC.read_text(encoding="utf-8").split())
    metadata = dict(instances["MultiLunarLanderEnv"].metadata)
    shown = "{" + ", ".join(f'"{k}": {v!r}'.replace("'", '"') for k, v in metadata.items()) + "}"
    assert shown in text, shown
