"""Chat templates rendered with bounds: a hostile template is a one-line error within seconds, never a hang.

A model folder's chat template (`chat_template.jinja`, `chat_template.json`, `tokenizer_config.json`'s
`chat_template`) is Jinja code from whoever made the folder. transformers renders it in Jinja's sandbox, which
stops attribute escapes but bounds neither time nor size: `{% for i in range(99999) %}{% for j in range(99999) %}`
loops for hours, a macro that calls itself twice doubles its work per level, `{{ 'x' * 10**10 }}` allocates 10 GB,
and `10 ** 10 ** 10` hangs already when the template is compiled (Jinja folds constant expressions).

`render_chat` renders with the same environment transformers builds (`ImmutableSandboxedEnvironment`, trim_blocks,
lstrip_blocks, loop controls, the `generation` tag, `tojson` without HTML escaping, `raise_exception`,
`strftime_now`, `dict`, `namespace`) and the same variables (`messages`, `tools`, `documents`,
`add_generation_prompt` and the tokenizer's special tokens), so a well-behaved template renders the same text
(tests/test_hardening_sizes.py compares it with `processor.apply_chat_template`), but:

- every loop step, call, arithmetic operator, filter and output is a step: at most `MAX_STEPS` per render, and
  rendering stops after `MAX_SECONDS`;
- before an operation that can grow a value (`*`, `+`, `**`, `%`, `~`, `join`, `replace`, `center`, `indent`,
  `tojson`, `str.ljust`, ...) runs, the size of its result is predicted and refused above `MAX_VALUE_CELLS`
  (characters, or items of a list); all values made in one render add up to at most `MAX_CREATED_CELLS`, and the
  rendered text to at most `MAX_OUTPUT_CHARS`; integer arguments of calls and filters are at most `MAX_INT_ARG`
  and integers at most `MAX_INT_BITS` bits;
- nothing is folded at compile time that could be large (operators and filters are evaluated when rendering,
  under the bounds).

The bounds are far above what any real template needs (the tiny models' templates take ~100 steps).

Example:
    text = render_chat(processor.chat_template, messages, add_generation_prompt=True,
                       special_tokens=processor.tokenizer.special_tokens_map)
"""

from __future__ import annotations

import contextvars
import functools
import itertools
import json
import operator
import re
import time
from datetime import datetime
from typing import Any

from degusta_learn.errors import DegustaError

MAX_TEMPLATE_CHARS = 1_000_000
"""Longest template text (the longest real templates, with tool calling, are ~20,000 characters)."""
MAX_OUTPUT_CHARS = 4_000_000
"""Longest rendered text (about a million tokens: beyond every model's context)."""
MAX_VALUE_CELLS = MAX_OUTPUT_CHARS
"""Largest value an operation may make: characters of a string, items (and their characters) of a list or dict."""
MAX_CREATED_CELLS = 16 * MAX_OUTPUT_CHARS
"""All values made in one render together (bounds its memory)."""
MAX_STEPS = 1_000_000
"""Loop steps, calls, operators, filters and outputs of one render."""
MAX_SECONDS = 2.0
"""Wall-clock limit of one render (a real one takes well under 10 ms, 200 times less)."""
MAX_INT_ARG = 1_000_000
"""Largest integer argument of a call or filter (a width, a count, a range end)."""
MAX_INT_BITS = 128
"""Largest integer an operator may make or take."""


class TemplateLimit(Exception):
    """A bound that a template's rendering reached (the message says which)."""


class _Budget:
    __slots__ = ("steps", "created", "deadline")

    def __init__(self, seconds: float):
        self.steps = 0
        self.created = 0
        self.deadline = time.monotonic() + seconds

    def step(self) -> None:
        self.steps += 1
        if self.steps > MAX_STEPS:
            raise TemplateLimit(f"more than {MAX_STEPS:,} loop steps, calls and operations in one render "
                                "(a loop or recursion without end?)")
        if not self.steps & 63 and time.monotonic() > self.deadline:
            raise TemplateLimit(f"rendering took more than {MAX_SECONDS:g} s (a loop or recursion without end?)")

    def create(self, cells: int) -> None:
        _check_cells(cells)
        self.created += cells
        if self.created > MAX_CREATED_CELLS:
            raise TemplateLimit(f"the values made while rendering exceed {MAX_CREATED_CELLS:,} characters in all "
                                "(a value that grows in a loop?)")


_BUDGET: contextvars.ContextVar[_Budget | None] = contextvars.ContextVar("degusta_template_budget", default=None)


def _budget() -> _Budget:
    budget = _BUDGET.get()
    if budget is None:  # outside render_chat, e.g. Jinja folding a constant at compile time: not done
        raise TemplateLimit("not inside a bounded render")
    return budget


def _check_cells(cells: int, what: str = "a value") -> None:
    if cells > MAX_VALUE_CELLS:
        raise TemplateLimit(f"{what} of more than {MAX_VALUE_CELLS:,} characters or items (at least {cells:,})")


def _weight(value: Any, limit: int = MAX_VALUE_CELLS) -> tuple[int, int]:
    """(cells, depth): characters of strings plus items of containers, counting shared items each time (as `str`
    or `tojson` would write them), and the nesting depth; stops counting once past `limit` (so its cost is at most
    `limit` items, whatever the value)."""
    total, depth, seen = 0, 0, 0
    budget = _BUDGET.get()
    stack = [(iter((value,)), 1)]
    while stack:
        seen += 1
        if not seen & 0xFFFF and budget is not None and time.monotonic() > budget.deadline:
            raise TemplateLimit(f"rendering took more than {MAX_SECONDS:g} s (a value that grows in a loop?)")
        it, d = stack[-1]
        x = next(it, _END)
        if x is _END:
            stack.pop()
            continue
        if isinstance(x, (str, bytes)):
            total += len(x)
        elif isinstance(x, dict):
            total += 1 + len(x)
            depth = max(depth, d)
            stack.append((itertools.chain(x.keys(), x.values()), d + 1))
        elif isinstance(x, (list, tuple, set, frozenset)):
            total += 1 + len(x)
            depth = max(depth, d)
            stack.append((iter(x), d + 1))
        else:
            total += 1
        if total > limit:
            break
    return total, depth


_END = object()


def _cells(value: Any) -> int:
    return _weight(value)[0]


def _check_int(value: Any, bits: int = MAX_INT_BITS) -> None:
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > bits:
        raise TemplateLimit(f"an integer of {value.bit_length():,} bits (at most {bits})")


def _check_args(args, kwargs) -> None:
    for v in (*args, *kwargs.values()):
        if isinstance(v, int) and not isinstance(v, bool) and abs(v) > MAX_INT_ARG:
            raise TemplateLimit(f"an argument of {_show_int(v)} (arguments are at most {MAX_INT_ARG:,})")


def _show_int(v: int) -> str:
    return f"{v:,}" if v.bit_length() < 64 else f"an integer of {len(str(abs(v))) if v.bit_length() < 10_000 else 'many'} digits"


_WIDTH = re.compile(r"\d{7,}")


def _check_format(fmt: Any) -> None:
    """A %-format or str.format string whose widths or precisions ask for a million characters or more."""
    if isinstance(fmt, str) and _WIDTH.search(fmt):
        raise TemplateLimit("a format width or precision of 7 or more digits")


def _predict_replace(s: Any, old: Any, new: Any, count: Any = -1) -> None:
    if not (isinstance(s, str) and isinstance(old, str) and isinstance(new, str)):
        return
    n = len(s) + 1 if old == "" else s.count(old)
    if isinstance(count, int) and not isinstance(count, bool) and count >= 0:
        n = min(n, count)
    _check_cells(len(s) + n * (len(new) - len(old)), "a replace result")


def _predict_join(sep: Any, items: list) -> None:
    _check_cells(sum(_cells(i) for i in items) + len(str(sep)) * max(0, len(items) - 1), "a join result")


def _listed(iterable: Any) -> list:
    """The items of `iterable` as a list, one step each (a join or sum of a lazy map/select)."""
    budget = _budget()
    out = []
    for item in iterable:
        budget.step()
        out.append(item)
        if len(out) > MAX_VALUE_CELLS:
            _check_cells(len(out), "a sequence")
    return out


# -- filters ---------------------------------------------------------------------------------------------------
_GROWING_6X = {"string", "pprint", "e", "escape", "forceescape", "urlencode", "xmlattr", "title", "capitalize",
               "upper", "lower", "trim", "striptags", "filesizeformat", "urlize"}


def _predict_filter(name: str, args: list, kwargs: dict) -> list:
    """Refuse a filter call whose result would be too large; returns the arguments to call it with."""
    if not args:
        return args
    value, rest = args[0], args[1:]

    def arg(i: int, kw: str, default=None):
        return rest[i] if len(rest) > i else kwargs.get(kw, default)

    if name == "center":
        width = arg(0, "width", 80)
        _check_cells(max(len(str(value)), width if isinstance(width, int) else 0), "a center result")
    elif name == "indent":
        width = arg(0, "width", 4)
        pad = width if isinstance(width, int) and not isinstance(width, bool) else len(str(width))
        s = str(value)
        _check_cells(len(s) + (s.count("\n") + 1) * pad, "an indent result")
    elif name == "wordwrap":
        wrap = arg(2, "wrapstring", None) or "\n"
        s = str(value)
        _check_cells(len(s) + (len(s) + 1) * len(str(wrap)), "a wordwrap result")
    elif name == "replace":
        _predict_replace(value if isinstance(value, str) else str(value), arg(0, "old", ""), arg(1, "new", ""),
                         arg(2, "count", -1))
    elif name == "join":
        items = _listed(value)
        _predict_join(arg(0, "d", ""), items)
        return [items, *rest]
    elif name == "format":
        _check_format(value)
    elif name == "sum":
        items = _listed(value)
        if any(isinstance(i, (str, bytes, list, tuple, dict)) for i in items) or not isinstance(
                arg(1, "start", 0), (int, float)):
            raise TemplateLimit("sum of strings or lists (only numbers are summed)")
        return [items, *rest]
    elif name == "tojson":
        cells, depth = _weight(value)
        indent = arg(1, "indent", None)
        width = indent if isinstance(indent, int) and not isinstance(indent, bool) else len(indent or "")
        _check_cells(cells * (6 + width * depth), "a tojson result")
    elif name in _GROWING_6X:
        _check_cells(6 * _cells(value), f"a {name} result")
    return args


def _bounded_filter(name: str, fn):
    pass_arg = getattr(fn, "jinja_pass_arg", None)

    @functools.wraps(fn)
    def bounded(*args, **kwargs):
        budget = _budget()
        budget.step()
        lead, rest = (args[:1], list(args[1:])) if pass_arg is not None else ((), list(args))
        _check_args(rest[1:], kwargs)
        rest = _predict_filter(name, rest, kwargs)
        result = fn(*lead, *rest, **kwargs)
        if hasattr(result, "__next__"):  # map, select, batch, ...: one step per item
            return _counted(result)
        budget.create(_cells(result))
        return result

    return bounded


def _counted(iterator):
    budget = _budget()
    for item in iterator:
        budget.step()
        yield item


# -- the environment -------------------------------------------------------------------------------------------
_ARITHMETIC = {"+": operator.add, "-": operator.sub, "*": operator.mul, "/": operator.truediv,
               "//": operator.floordiv, "%": operator.mod, "**": operator.pow}
_SEQUENCES = (str, bytes, list, tuple)


def _environment():
    import jinja2
    from jinja2 import nodes
    from jinja2.ext import Extension, loopcontrols
    from jinja2.runtime import LoopContext
    from jinja2.sandbox import ImmutableSandboxedEnvironment
    from jinja2.visitor import NodeTransformer

    def env_call(name: str, args: list, lineno: int) -> nodes.Call:
        return nodes.Call(nodes.EnvironmentAttribute(name), list(args), [], None, None, lineno=lineno)

    class Bounder(NodeTransformer):
        """Route loops, `~` and literal output through the environment's counting methods."""

        def visit_For(self, node):
            self.generic_visit(node)
            node.iter = env_call("degusta_iter", [node.iter], node.lineno)
            return node

        def visit_Concat(self, node):
            self.generic_visit(node)
            return env_call("degusta_concat", node.nodes, node.lineno)

        def visit_Output(self, node):
            self.generic_visit(node)
            literal = sum(len(c.data) for c in node.nodes if isinstance(c, nodes.TemplateData))
            if literal:  # literal text is written without `finalize`: charged here, each time it is written
                node.nodes.insert(0, env_call("degusta_emit", [nodes.Const(literal, lineno=node.lineno)],
                                              node.lineno))
            return node

    class Generation(Extension):
        """transformers' `{% generation %}...{% endgeneration %}` tag (marks assistant text): renders its body."""

        tags = {"generation"}

        def parse(self, parser):
            lineno = next(parser.stream).lineno
            body = parser.parse_statements(("name:endgeneration",), drop_needle=True)
            return nodes.CallBlock(self.call_method("_body"), [], [], body).set_lineno(lineno)

        def _body(self, caller):
            return caller()

    class Namespace(jinja2.utils.Namespace):
        """transformers' namespace: no underscore-prefixed attributes."""

        def __init__(*args, **kwargs):
            self, args = args[0], args[1:]
            attrs = dict(*args, **kwargs)
            for name in attrs:
                Namespace._check_name(name)
            jinja2.utils.Namespace.__init__(self, attrs)

        def __setitem__(self, name, value):
            Namespace._check_name(name)
            jinja2.utils.Namespace.__setitem__(self, name, value)

        @staticmethod
        def _check_name(name):
            if isinstance(name, str) and name.startswith("_"):
                raise jinja2.exceptions.SecurityError(f"chat templates cannot store underscore-prefixed "
                                                      f"attributes on a namespace, got {name!r}")

    class TemplateDict:
        def __call__(self, *args, **kwargs):
            return dict(*args, **kwargs)

        def fromkeys(self, *args, **kwargs):
            return dict.fromkeys(*args, **kwargs)

    def raise_exception(message):
        raise jinja2.exceptions.TemplateError(message)

    def tojson(x, ensure_ascii=False, indent=None, separators=None, sort_keys=False):
        return json.dumps(x, ensure_ascii=ensure_ascii, indent=indent, separators=separators, sort_keys=sort_keys)

    def strftime_now(format):
        return datetime.now().strftime(format)

    class BoundedEnvironment(ImmutableSandboxedEnvironment):
        intercepted_binops = frozenset(_ARITHMETIC)

        def _parse(self, source, name, filename):
            tree = Bounder().visit(super()._parse(source, name, filename))
            tree.set_environment(self)
            return tree

        def call_binop(self, context, op, left, right):
            budget = _budget()
            budget.step()
            _check_int(left)
            _check_int(right)
            if op == "*":
                seq, n = (left, right) if isinstance(left, _SEQUENCES) else (right, left)
                if isinstance(seq, _SEQUENCES) and isinstance(n, int):
                    _check_cells(_cells(seq) * max(n, 0), "a repeated sequence")
            elif op == "**":
                if isinstance(left, int) and isinstance(right, int) and right > 0 and abs(left) > 1 \
                        and left.bit_length() * right > MAX_INT_BITS:
                    raise TemplateLimit(f"a power of more than {MAX_INT_BITS} bits")
            elif op == "+":
                if isinstance(left, _SEQUENCES) and isinstance(right, _SEQUENCES):
                    size = _cells(left)
                    _check_cells(size + (size if right is left else _cells(right)), "a concatenation")
            elif op == "%" and isinstance(left, str):
                _check_format(left)
                _check_args(right if isinstance(right, tuple) else (right,), {})
            result = _ARITHMETIC[op](left, right)
            _check_int(result)
            if isinstance(result, _SEQUENCES):
                budget.create(_cells(result))
            return result

        def call(__self, __context, __obj, *args, **kwargs):  # noqa: N805 - Jinja's signature
            budget = _budget()
            budget.step()
            if isinstance(__obj, LoopContext) and args:  # `loop(children)` of a recursive loop: count its steps
                args = (__self.degusta_iter(args[0]), *args[1:])
            elif getattr(__obj, "__self__", None) is not __self:
                _check_args(args, kwargs)
                args = _predict_method(__obj, args, kwargs)
            result = super().call(__context, __obj, *args, **kwargs)
            if isinstance(result, (str, bytes, list, tuple, dict)):
                budget.create(_cells(result))
            return result

        def degusta_iter(self, iterable):
            budget = _budget()
            for item in iterable:
                budget.step()
                yield item

        def degusta_concat(self, *items):
            budget = _budget()
            _check_cells(sum(_cells(i) for i in items), "a ~ concatenation")
            result = "".join(map(str, items))
            budget.create(len(result))
            return result

        def degusta_emit(self, literal: int) -> str:
            budget = _budget()
            budget.create(literal)
            return ""

    def finalize(value):
        budget = _budget()
        budget.step()
        budget.create(_cells(value))
        return value

    env = BoundedEnvironment(trim_blocks=True, lstrip_blocks=True, extensions=[Generation, loopcontrols],
                             finalize=finalize)
    env.filters["tojson"] = tojson
    env.globals.update(raise_exception=raise_exception, strftime_now=strftime_now, dict=TemplateDict(),
                       namespace=Namespace)
    env.filters = {name: _bounded_filter(name, fn) for name, fn in env.filters.items()}
    return env


def _predict_method(obj, args: tuple, kwargs: dict) -> tuple:
    """Refuse a call of a string method (or `lipsum`) whose result would be too large; returns the arguments."""
    obj = getattr(obj, "__wrapped__", obj)  # the sandbox wraps str.format / format_map
    owner, name = getattr(obj, "__self__", None), getattr(obj, "__name__", "")
    if name == "generate_lorem_ipsum":  # Jinja's `lipsum(n=5, html=True, min=20, max=100)`: n paragraphs of words
        params = {"n": 5, "max": 100, **dict(zip(("n", "html", "min", "max"), args)), **kwargs}
        if isinstance(params["n"], int) and isinstance(params["max"], int):
            _check_cells(12 * max(params["n"], 0) * max(params["max"], 0), "a lipsum text")
        return args
    if not isinstance(owner, str):
        return args
    if name == "replace" and len(args) >= 2:
        _predict_replace(owner, args[0], args[1], args[2] if len(args) > 2 else kwargs.get("count", -1))
    elif name == "join" and args:
        items = _listed(args[0])
        _predict_join(owner, items)
        return (items, *args[1:])
    elif name in ("center", "ljust", "rjust", "zfill") and args and isinstance(args[0], int):
        _check_cells(max(len(owner), args[0]), f"a {name} result")
    elif name == "expandtabs":
        size = args[0] if args else kwargs.get("tabsize", 8)
        if isinstance(size, int):
            _check_cells(len(owner) + owner.count("\t") * max(size, 0), "an expandtabs result")
    elif name in ("format", "format_map"):
        _check_format(owner)
    elif name == "translate" and args and isinstance(args[0], dict):
        longest = max((_cells(v) for v in args[0].values()), default=1)
        _check_cells(len(owner) * max(longest, 1), "a translate result")
    elif name == "encode":
        _check_cells(4 * len(owner), "an encoded string")
    return args


@functools.lru_cache(maxsize=1)
def environment():
    """The one bounded environment (built on first use; Jinja is imported then)."""
    return _environment()


@functools.lru_cache(maxsize=32)
def compile_template(text: str):
    """The compiled template of `text`; TemplateLimit for a text over MAX_TEMPLATE_CHARS or nested too deeply, Jinja's
    TemplateSyntaxError for one that does not parse."""
    if not isinstance(text, str):
        raise TemplateLimit(f"the chat template is a {type(text).__name__}, not text")
    if len(text) > MAX_TEMPLATE_CHARS:
        raise TemplateLimit(f"the chat template has {len(text):,} characters (at most {MAX_TEMPLATE_CHARS:,})")
    try:
        return environment().from_string(text)
    except (RecursionError, MemoryError):
        raise TemplateLimit("the chat template is nested too deeply to compile") from None


def render(text: str, seconds: float = MAX_SECONDS, **variables) -> str:
    """Render template `text` with `variables` under the bounds (TemplateLimit when one is reached; the template's
    own errors as Jinja raises them)."""
    template = compile_template(text)
    token = _BUDGET.set(_Budget(seconds))
    try:
        out, n = [], 0
        for chunk in template.generate(**variables):
            n += len(chunk)
            if n > MAX_OUTPUT_CHARS:
                raise TemplateLimit(f"the rendered text exceeds {MAX_OUTPUT_CHARS:,} characters")
            out.append(chunk)
        return "".join(out)
    except RecursionError:
        raise TemplateLimit("recursion too deep (a macro or loop that calls itself without end?)") from None
    finally:
        _BUDGET.reset(token)


def render_chat(template: str | dict, messages: list[dict], add_generation_prompt: bool = False,
                special_tokens: dict | None = None, what: str = "model: its chat template") -> str:
    """The chat `messages` as the template writes them (what `processor.apply_chat_template(messages,
    add_generation_prompt=..., tokenize=False)` returns for a well-behaved template), bounded; a DegustaError
    starting with `what` (one line) for a template that breaks a bound, raises or fails."""
    import jinja2

    if isinstance(template, dict):  # several named templates: the default one, as transformers picks it
        if "default" not in template:
            raise DegustaError(f"{what}: the processor has several chat templates ({', '.join(map(str, template))}) "
                               "and none is named 'default'")
        template = template["default"]
    variables = {**(special_tokens or {}), "messages": messages, "tools": None, "documents": None,
                 "add_generation_prompt": add_generation_prompt}
    try:
        return render(template, **variables)
    except TemplateLimit as e:
        raise DegustaError(f"{what} was stopped: {e}") from None
    except jinja2.TemplateError as e:
        raise DegustaError(f"{what} cannot render a message ({type(e).__name__}: {_first(e)})") from None
    except DegustaError:
        raise
    except Exception as e:  # noqa: BLE001 - template code may raise anything (a TypeError, a KeyError, ...)
        raise DegustaError(f"{what} cannot render a message ({type(e).__name__}: {_first(e)})") from None


def check_template(text: Any, where: str) -> None:
    """Refuse (one line starting with `where`) a template text that breaks a bound when rendering plain
    conversations; a template that merely does not parse or raises is left to the loader and ChatFormat."""
    probes = ([{"role": "user", "content": [{"type": "text", "text": "x"}]}],
              [{"role": "user", "content": [{"type": "text", "text": "x"}]},
               {"role": "assistant", "content": [{"type": "text", "text": "y"}]},
               {"role": "user", "content": "z"}])
    try:
        for messages in probes:
            for add in (True, False):
                render(text, messages=messages, tools=None, documents=None, add_generation_prompt=add)
    except TemplateLimit as e:
        raise DegustaError(f"{where}: chat template refused: {e}") from None
    except Exception:  # noqa: BLE001 - a syntax error or a raise_exception is no bound: ChatFormat reports it
        return


def _first(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return (text[0] if text else "")[:200]
