"""Build a graph in Python, save it as JSON and run it: a Live Link Face take onto the ICT head,
written as an animated glTF and USD.

Run: python examples/build_graph.py TAKE.csv OUT_FOLDER

The same graph as a file is what `Graph.save` writes (OUT_FOLDER/take_to_gltf.json): run it
again with `nodegraph run OUT_FOLDER/take_to_gltf.json take=other.csv`.
"""

from __future__ import annotations

import sys
from pathlib import Path

import nodegraph
from nodegraph import Graph


def build(take: str, folder: Path) -> Graph:
    """take.csv -> io.LoadLiveLinkCSV -> export.GltfAnimation and export.UsdAnimation on the ICT head."""
    graph = Graph()
    model = graph.add("io.LoadFaceModel", "model")
    load = graph.add("io.LoadLiveLinkCSV", "take", path=take)
    gltf = graph.add("export.GltfAnimation", "gltf", path=str(folder / "take.glb"))
    usd = graph.add("export.UsdAnimation", "usd", path=str(folder / "take.usdc"))
    graph.connect(model["model"], load["model"])
    for writer in (gltf, usd):
        graph.connect(load["performance"], writer["performance"])
        graph.connect(model["model"], writer["model"])
    graph.expose("take", load, "path", "Live Link Face CSV take")
    return graph


def main(argv: list[str]) -> int:
    if len(argv) != 3:
        print(__doc__)
        return 2
    folder = Path(argv[2])
    graph = build(argv[1], folder)
    folder.mkdir(parents=True, exist_ok=True)
    graph.save(folder / "take_to_gltf.json")
    result = nodegraph.run(graph, cache=False)
    print(result.summary())
    return result.exit_code


if __name__ == "__main__":
    sys.exit(main(sys.argv))
