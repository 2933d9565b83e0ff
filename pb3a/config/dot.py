"""Drawing a plan as Graphviz DOT: what runs where, and what feeds what.

One cluster per node; each module is a record with its inputs on the left,
its instance path and class in the middle, its outputs on the right; each link
is an edge from output to input, labelled with its policy when not ``latest``.
Each macro instance is a dashed cluster inside its node's, labelled with its path
and its macro (the Macro class's name, or ``[macros.NAME]``), holding its modules
and, nested again, its child macros. A cluster cannot cross nodes, so a macro whose
modules run on several nodes is drawn as one cluster per node, each holding the
part on its node, with the same path and macro and the nodes the rest runs on.
"""

from __future__ import annotations

import re

from pb3a.config.plan import FlatModule, Plan, split_by_macro

_RECORD_SPECIAL = re.compile(r"([{}|<> ])")
_MACRO_STYLE = ('style="dashed,rounded"; color="gray35"; fontcolor="gray20"; fontsize=11; '
                'labeljust=l;')


def plan_to_dot(plan: Plan) -> str:
    """The DOT text of ``plan``."""
    lines = [f"digraph {_quote(plan.name)} {{",
             "  rankdir=LR;",
             '  node [shape=Mrecord, fontname="Helvetica", fontsize=10];',
             '  edge [fontname="Helvetica", fontsize=9];',
             '  fontname="Helvetica";']
    for node in plan.nodes.values():
        title = f"node {node.name}"
        if node.address:
            title += f"\\n{node.address}"
        if node.workers:
            title += f"\\n{node.workers} worker process{'es' if node.workers > 1 else ''}"
        lines += [f"  subgraph {_quote('cluster_' + node.name)} {{",
                  f"    label={_quote(title)};",
                  "    style=rounded;"]
        lines += _members(plan, node.name,
                          [m.name for m in plan.modules.values() if m.node == node.name],
                          "", "    ")
        lines.append("  }")
    for link in plan.links:
        attrs = f" [label={_quote(str(link.policy))}]" if link.policy.kind != "latest" else ""
        lines.append(f"  {_quote(link.src)}:{_quote('o_' + link.src_port)} -> "
                     f"{_quote(link.dst)}:{_quote('i_' + link.dst_port)}{attrs};")
    lines.append("}")
    return "\n".join(lines) + "\n"


def _members(plan: Plan, node: str, names: list[str], prefix: str, indent: str) -> list[str]:
    """The modules ``names`` of ``node``, all below macro path ``prefix``: those directly
    in it as records, those of each child macro inside that macro's cluster."""
    direct, below = split_by_macro(names, prefix)
    lines = [f"{indent}{_quote(name)} [label={_quote(_record(plan.modules[name]))}];"
             for name in direct]
    for macro, inside in below.items():
        lines += [f"{indent}subgraph {_quote(f'cluster_{node}/{macro}')} {{",
                  f"{indent}  label={_quote(_macro_title(plan, macro, node))};",
                  f"{indent}  {_MACRO_STYLE}",
                  *_members(plan, node, inside, macro + "/", indent + "  "),
                  f"{indent}}}"]
    return lines


def _macro_title(plan: Plan, macro: str, node: str) -> str:
    """The macro's path, its macro, and the nodes the rest of it runs on, if any: lines
    ended by ``\\l``, left-aligned as the label is."""
    lines = [macro, plan.macros[macro]] if macro in plan.macros else [macro]
    elsewhere = {m.node for m in plan.modules.values() if m.name.startswith(macro + "/")}
    others = [name for name in plan.nodes if name in elsewhere and name != node]
    if others:
        lines.append(f"(part: the rest on node{'s' if len(others) > 1 else ''} "
                     f"{', '.join(others)})")
    return "".join(line + "\\l" for line in lines)


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
