"""Every integer option and argument of the command line takes only an optional '-' and ASCII digits 0-9.

Python's ``int()`` (and pydantic's lax integer parsing, which typer uses) read "1_0" as 10, "+3" and " 3 " as 3,
"1.0" as 1 and, in ``int()``, "٣" or "３" as 3: a hostile-input trial found ``--revision 1_0`` silently read as
revision 10. Each such value is a usage error (exit 2) naming the option and the value. The integer parameters are
found by walking the command tree, so an integer option added later is covered without touching this file.
"""

from __future__ import annotations

import pytest
import typer.main

from cli_run import one_error, run_cli
from driftmap.cli import app

REFUSED = ("1_0", "+1", "١", "1e1", " 1", "1 ", "1.0", "３", "0x10", "", "-", "1\n", "¹")
"""Values ``int()`` or pydantic take (or would) that are not '-'? followed by ASCII digits."""


def _root():
    return typer.main.get_command(app)


def _is_int(param) -> bool:  # noqa: ANN001 - a typer (or click) parameter
    descriptor = getattr(param, "type_descriptor", None)
    if descriptor is not None:  # typer >= 0.2x: the annotation decides how the value is parsed
        annotation = descriptor.annotation
        args = getattr(annotation, "__args__", None)
        if args and getattr(annotation, "__origin__", None) in (list, tuple):
            return all(a is int for a in args if a is not Ellipsis)
        return annotation is int
    import click  # older typer on click: INT or IntRange

    return isinstance(getattr(param, "type", None), click.types.IntParamType)


def _int_params() -> list[tuple[str, object]]:
    """(command, parameter) for every integer parameter of every command (and of the group itself)."""
    root = _root()
    ctx = root.make_context("driftmap", [], resilient_parsing=True)
    found = [("", p) for p in root.params if _is_int(p)]
    for name in root.list_commands(ctx):
        found += [(name, p) for p in root.get_command(ctx, name).params if _is_int(p)]
    return found


INT_PARAMS = _int_params()


def _id(item: tuple[str, object]) -> str:
    name, param = item
    return f"{name or 'driftmap'}:{(param.opts or [param.name])[0]}"


def test_the_walk_finds_the_integer_options() -> None:
    """The discovery itself: the options the trial named, the ranged ones and the Optional ones are all found."""
    ids = {_id(item) for item in INT_PARAMS}
    for expected in ("export:--revision", "export:--session", "diagnose:--revision", "diagnose:--compare-revision",
                     "diagnose:--points-per-frame", "view:--revision", "view:--reference", "perturb:--step-frame",
                     "synth:--frames", "synth:--seed", "synth:--fleet", "synth:--broken", "demo:--frames",
                     "build:--threads", "batch:--workers", "rollback:--to", "decide:--revision",
                     "decide:--against-revision"):
        assert expected in ids, (expected, sorted(ids))
    assert "build:--frames" not in ids  # build's --frames is a START:STOP[:STEP] slice (text), checked by its reader


def _args(param, value: str) -> list[str]:  # noqa: ANN001
    """The command's arguments giving ``value`` to ``param`` (and nothing else)."""
    if param.param_type_name == "option":
        return [param.opts[0], value]  # the word after the flag is its value, even "-1" or ""
    return ["--", value]  # an argument: after '--', so "-1" is not read as an option


def _command(name: str):  # noqa: ANN202
    root = _root()
    return root.get_command(root.make_context("driftmap", [], resilient_parsing=True), name) if name else root


def _usage_error(name: str, param, value: str) -> str:  # noqa: ANN001
    """Parse ``value`` for ``param`` as the command line does (``make_context``: parsing only, the command never
    runs) and return the usage error's message; it must be click's usage error (exit code 2)."""
    with pytest.raises(Exception) as caught:  # noqa: PT011 - the vendored click's UsageError, checked below
        _command(name).make_context(name or "driftmap", _args(param, value))
    exc = caught.value
    assert getattr(exc, "exit_code", None) == 2 and hasattr(exc, "format_message"), (value, repr(exc))
    return " ".join(exc.format_message().split())


@pytest.mark.parametrize("item", INT_PARAMS, ids=_id)
def test_every_integer_option_refuses_what_int_would_stretch(item) -> None:  # noqa: ANN001
    name, param = item
    hint = param.opts[0] if param.param_type_name == "option" else (param.metavar or param.name)
    for value in REFUSED:
        text = _usage_error(name, param, value)
        assert f"Invalid value for '{hint}': {value!r} is not an integer (ASCII digits only)" in text, (value, text)


def _valid(param) -> list[str]:  # noqa: ANN001
    lo = getattr(param, "min", None)
    hi = getattr(param, "max", None)
    values = ["0", "10", "-1", "007", "-0", "12345678901234567890"]
    values += [str(b) for b in (lo, hi) if b is not None]
    return [v for v in values if (lo is None or int(v) >= lo) and (hi is None or int(v) <= hi)]


@pytest.mark.parametrize("item", INT_PARAMS, ids=_id)
def test_plain_integers_still_parse(item) -> None:  # noqa: ANN001
    """'0', '10', '-1' (where the range allows) and each range's bounds are read as those integers."""
    name, param = item
    command = _command(name)
    for value in _valid(param):
        ctx = command.make_context(name or "driftmap", _args(param, value), resilient_parsing=True)
        got = ctx.params[param.name]
        got = got[0] if isinstance(got, (list, tuple)) else got
        assert got == int(value) and type(got) is int, (value, got)


@pytest.mark.parametrize("item", [i for i in INT_PARAMS if i[1].min is not None or i[1].max is not None], ids=_id)
def test_the_ranges_still_refuse(item) -> None:  # noqa: ANN001
    """Plain integers outside an option's range keep the range's usage error."""
    name, param = item
    for bound, beyond, words in ((param.min, -1, "greater than or equal"), (param.max, +1, "less than or equal")):
        if bound is not None:
            text = _usage_error(name, param, str(bound + beyond))
            assert f"Invalid value for '{param.opts[0]}'" in text and f"{words} to {bound}" in text, text


# through the real command line, as a user runs it


@pytest.mark.parametrize("command, output", [("diagnose", "--json"), ("export", "--trajectory")])
def test_revision_1_0_is_not_revision_10(command: str, output: str, tmp_path) -> None:  # noqa: ANN001
    """The trial's case: `--revision 1_0` was revision 10; now it is refused before the store is opened."""
    for value in ("1_0", "+1", "١", " 1", "1.0", "1e1"):
        out = run_cli(command, tmp_path, output, tmp_path / "out", "--revision", value, cwd=tmp_path)
        assert out.returncode == 2, (value, out.returncode, out.stderr)
        line = one_error(out)
        assert f"Invalid value for '--revision': {value!r} is not an integer (ASCII digits only)" in line, line
    assert not (tmp_path / "out").exists()


def test_frames_and_threads_through_the_command_line(tmp_path) -> None:  # noqa: ANN001
    """`synth --frames` and `build --threads` as a user types them: strict digits, and the ranges keep their
    messages."""
    out = run_cli("synth", tmp_path / "log", "--frames", "1_0")
    assert out.returncode == 2 and not (tmp_path / "log").exists()
    assert "Invalid value for '--frames': '1_0' is not an integer (ASCII digits only)" in one_error(out)
    out = run_cli("synth", tmp_path / "log", "--frames", "1")
    assert out.returncode == 2, out.stderr
    line = one_error(out)
    assert "Invalid value for '--frames'" in line and "greater than or equal to 2" in line, line
    for value, words in (("+2", "'+2' is not an integer (ASCII digits only)"), ("0", "greater than or equal to 1")):
        out = run_cli("build", tmp_path, "--out", tmp_path / "s", "--threads", value)
        assert out.returncode == 2, out.stderr
        line = one_error(out)
        assert "Invalid value for '--threads'" in line and words in line, line
    assert not (tmp_path / "s").exists()
