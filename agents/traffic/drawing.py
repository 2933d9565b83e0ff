"""Pictures of road networks for the docs: every road as its lanes' outline, the
signalized junctions marked and named, drawn with matplotlib from the built network
(read by sumolib).

    python -m agents.traffic.drawing scenarios/traffic/ring.toml docs/traffic_ring.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

from agents.traffic.networks import Network


def draw_network(description: Path, output: Path, cache: Path | None = None) -> Path:
    """Draw the network described at ``description`` to ``output`` (PNG)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import sumolib

    network = Network.load(description)
    net = sumolib.net.readNet(str(network.build("static", cache)))
    figure, axes = plt.subplots(figsize=(7, 5.5), dpi=110)
    pairs = {(e.getFromNode().getID(), e.getToNode().getID()) for e in net.getEdges()}
    for edge in net.getEdges():
        shape = edge.getShape()
        xs, ys = zip(*shape, strict=True)
        width = 1.5 + 1.8 * edge.getLaneNumber()
        axes.plot(xs, ys, color="#9aa0a6", linewidth=width, solid_capstyle="round", zorder=1)
        axes.plot(xs, ys, color="white", linewidth=0.6, zorder=2)
        one_way = (edge.getToNode().getID(), edge.getFromNode().getID()) not in pairs
        if one_way:                          # its direction, on its middle segment
            middle = len(shape) // 2
            (x0, y0), (x1, y1) = shape[middle - 1], shape[middle]
            centre = ((x0 + x1) / 2, (y0 + y1) / 2)
            ahead = (centre[0] + (x1 - x0) * 0.1, centre[1] + (y1 - y0) * 0.1)
            axes.annotate("", xy=ahead, xytext=centre, zorder=3, arrowprops={
                "arrowstyle": "-|>,head_width=0.4,head_length=0.8", "color": "#1a73e8"})
    lights = [node for node in net.getNodes() if node.getType() == "traffic_light"]
    for node in lights:
        x, y = node.getCoord()
        axes.scatter([x], [y], s=130, color="#d93025", edgecolors="black", zorder=4)
        axes.annotate(node.getID(), (x, y), xytext=(7, 7), textcoords="offset points",
                      fontsize=9, weight="bold", zorder=5)
    axes.set_aspect("equal")
    axes.set_title(f"{network.name}: {len(lights)} signalized junctions (red); one-way "
                   "roads arrowed (blue), the others two-way; width by lanes", fontsize=9)
    axes.set_xlabel("m")
    axes.set_ylabel("m")
    figure.tight_layout()
    output.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(output)
    plt.close(figure)
    return output


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("description", type=Path, help="the network's .toml file")
    parser.add_argument("output", type=Path, help="the PNG to write")
    args = parser.parse_args(argv)
    print(draw_network(args.description, args.output))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
