"""Drawing a plan as Graphviz DOT: what runs where, and what feeds what.

One cluster per node; each module is a record with its inputs on the left,
its instance path and class in the middle, its outputs on the right; each link
is an edge from output to input, labelled with its policy when not ``latest``.
"""

from __future__ import annotations

import re

from pb3a.config.plan import FlatModule, Plan

_RECORD_SPECIAL = re.compile(r"([{}|<> ])")


def plan_to_dot(plan: Plan) -> str:
    """The DOT text of ``plan``."""
    lines = [f"digraph {_quote(plan.name)} {{",
             "  rankdir=LR;",
             '  node [shape=Mrecord, fontname="Helvetica", fontsize=10];',
             '  edge [fontname="Helvetica", fontsize=9];']
    for node in plan.nodes.values():
        title = f"node {node.name}"
        if node.address:
            title += f"\\n{node.address}"
        if node.workers:
            title += f"\\n{node.workers} worker process{'es' if node.workers > 1 else ''}"
        lines += [f"  subgraph {_quote('cluster_' + node.name)} {{",
                  f"    label={_quote(title)};",
                  "    style=rounded;"]
        lines += [f"    {_quote(m.name)} [label={_quote(_record(m))}];"
                  for m in plan.modules.values() if m.node == node.name]
        lines.append("  }")
    for link in plan.links:
        attrs = f" [label={_quote(str(link.policy))}]" if link.policy.kind != "latest" else ""
        lines.append(f"  {_quote(link.src)}:{_quote('o_' + link.src_port)} -> "
                     f"{_quote(link.dst)}:{_quote('i_' + link.dst_port)}{attrs};")
    lines.append("}")
    return "\n".join(lines) + "\n"


def _record(module: FlatModule) -> str:
    """``{ {<i_x> x|...} | name\\nClass | {<o_y> y|...} }``: ports left and right of the name."""
    fields = []
    if module.cls.inputs:
        fields.append("{" + "|".join(f"<i_{p}> {_escape(p)}" for p in module.cls.inputs) + "}")
    middle = f"{_escape(module.name)}\\n{_escape(module.cls.__name__)}"
    if module.group:
        middle += f"\\ngroup {_escape(module.group)}"
    fields.append(middle)
    if module.cls.outputs:
        fields.append("{" + "|".join(f"<o_{p}> {_escape(p)}" for p in module.cls.outputs) + "}")
    return "{" + "|".join(fields) + "}"


def _escape(text: str) -> str:
    return _RECORD_SPECIAL.sub(r"\\\1", text)


def _quote(text: str) -> str:
    return '"' + text.replace('"', '\\"') + '"'
