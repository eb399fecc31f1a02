"""The documentation site's HTTP reference, written from the service's OpenAPI schema.

A MkDocs hook (``mkdocs.yml``: ``hooks``): at every build it makes the app with
:func:`flatserve.service.create_app` (no server is started: the schema is the app's
routes and models), and adds two generated files to the site, ``reference/http.md``
(every operation: its parameters, bodies and answers; then every schema) and
``reference/openapi.json`` (the schema itself, as the server's ``/openapi.json``
serves it). Offline: nothing is fetched.
"""
from __future__ import annotations

import json
from pathlib import Path

from mkdocs.structure.files import File

PAGE = "reference/http.md"
SCHEMA = "reference/openapi.json"
METHODS = ("get", "put", "post", "delete", "patch")


def openapi() -> dict:
    """The service's OpenAPI schema, as ``GET /openapi.json`` answers it."""
    from flatserve.service import Settings, create_app

    return create_app(Settings(data_dir=Path("unused"))).openapi()


def _text(text) -> str:
    """The schema's prose as Markdown text: brackets escaped (the schema has no links,
    and ``[+ 2] [+ 1]`` would read as a reference)."""
    return str(text or "").strip().replace("[", "\\[").replace("]", "\\]")


def _cell(text, prose: bool = True) -> str:
    """Text for one cell of a Markdown table (one line, pipes escaped); ``prose=False``
    for Markdown this module wrote (a type with its link)."""
    return " ".join((_text(text) if prose else str(text)).split()).replace("|", "\\|")


def _type(schema: dict) -> str:
    """A schema's type in a few words: ``string``, ``array of number``, a model's name."""
    if "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        return f"[{name}](#schema-{name.lower()})"
    for key in ("anyOf", "oneOf", "allOf"):
        if key in schema:
            return " or ".join(_type(s) for s in schema[key])
    kind = schema.get("type", "any")
    if kind == "array":
        return f"array of {_type(schema.get('items', {}))}"
    if "enum" in schema:
        return ", ".join(f"`{v}`" for v in schema["enum"])
    return kind


def _operation(path: str, method: str, op: dict) -> list[str]:
    out = [f"### {method.upper()} `{path}`", ""]
    if op.get("summary"):
        out += [f"**{_text(op['summary'])}**", ""]
    if op.get("description"):
        out += [_text(op["description"]), ""]
    params = op.get("parameters", [])
    if params:
        out += ["| parameter | in | type | required | what |", "|---|---|---|---|---|"]
        out += [f"| `{p['name']}` | {p['in']} | {_cell(_type(p.get('schema', {})), False)} | "
                f"{'yes' if p.get('required') else 'no'} | "
                f"{_cell(p.get('description') or p.get('schema', {}).get('description'))} |"
                for p in params]
        out.append("")
    body = op.get("requestBody")
    if body:
        out += ["| request body | schema |", "|---|---|"]
        out += [f"| `{ctype}` | {_cell(_type(c.get('schema', {})), False)} |"
                for ctype, c in body.get("content", {}).items()]
        out.append("")
    out += ["| status | what | body |", "|---|---|---|"]
    for status, r in op.get("responses", {}).items():
        types = ", ".join(f"`{t}`" for t in r.get("content", {}))
        out.append(f"| {status} | {_cell(r.get('description'))} | {types} |")
    return out + [""]


def _schema(name: str, s: dict) -> list[str]:
    out = [f"### {name} {{#schema-{name.lower()}}}", ""]
    if s.get("description"):
        out += [_text(s["description"]), ""]
    props = s.get("properties", {})
    if props:
        required = set(s.get("required", ()))
        out += ["| field | type | required | what |", "|---|---|---|---|"]
        out += [f"| `{k}` | {_cell(_type(v), False)} | {'yes' if k in required else 'no'} | "
                f"{_cell(v.get('description'))} |" for k, v in props.items()]
        out.append("")
    elif "enum" in s:
        out += [f"One of {_type(s)}.", ""]
    return out


def render(doc: dict) -> str:
    """The reference page (Markdown) of an OpenAPI schema."""
    info = doc.get("info", {})
    out = ["# HTTP reference", "",
           f"{info.get('title', '')} {info.get('version', '')}, OpenAPI {doc.get('openapi', '')}: "
           "written from the app's schema at every build of this site (the running server "
           "serves the same at `/openapi.json`, and `/docs` and `/redoc` render it). "
           "[The schema as JSON](openapi.json).", ""]
    if info.get("description"):
        out += [_text(info["description"]), ""]
    out += ["## Operations", ""]
    for path, item in doc.get("paths", {}).items():
        for method in METHODS:
            if method in item:
                out += _operation(path, method, item[method])
    out += ["## Schemas", ""]
    for name, s in doc.get("components", {}).get("schemas", {}).items():
        out += _schema(name, s)
    return "\n".join(out)


def on_files(files, config):
    """MkDocs hook: add the generated HTTP reference and the schema to the site."""
    doc = openapi()
    files.append(File.generated(config, PAGE, content=render(doc)))
    files.append(File.generated(config, SCHEMA, content=json.dumps(doc, indent=1)))
    return files
