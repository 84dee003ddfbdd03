"""The lumen's centreline tree from its voxels: trunk, root and descending ends, branches.

A first, coarse look at the lumen that tells the pipeline where to cut
(:mod:`~cgail_patient.prepare`); the simulator's own centrelines are computed later from
the finished wall (:func:`cgail_sim.centerline.compute_centerlines`).

1. 3-D thinning of the mask (scikit-image ``skeletonize``), a graph of the skeleton voxels
   (26-neighbours, edge length in mm), its largest component, and a minimum spanning tree (no
   cycles);
2. the inscribed radius at each skeleton voxel from the Euclidean distance transform;
3. pruning: a terminal path shorter than its junction's radius + ``spur_mm`` is a spur
   (a sinus lobe, a bump of the segmentation), removed until none is left;
4. :class:`SkeletonTree` keeps the pruned tree; which two ends are the aorta's (the trunk) is
   decided from the shape by :mod:`~cgail_patient.prepare` (the root is not always the
   widest end's partner: a whole-aorta label ends in iliac arteries narrower than the
   supra-aortic stubs), and :meth:`SkeletonTree.skeleton` makes the trunk between them, every
   other end a branch attached to the trunk at its junction.
"""

from __future__ import annotations

from dataclasses import dataclass
import itertools
from typing import Any

import numpy as np

from cgail_patient import PatientError
from cgail_patient.volume import LabelVolume

__all__ = ["Branch", "Skeleton", "SkeletonTree", "skeleton_tree"]


@dataclass(frozen=True)
class Branch:
    """A side branch from its junction on the trunk to its end."""

    points: np.ndarray
    """(P, 3) LPS mm from the junction (on the trunk) to the end."""
    radii: np.ndarray
    """(P,) inscribed radius, mm."""
    junction_index: int
    """Index of the junction in the trunk's points."""

    @property
    def length(self) -> float:
        """Path length from the junction to the end, mm."""
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())


@dataclass(frozen=True)
class Skeleton:
    """The trunk between the aorta's two ends and the branches off it (LPS mm)."""

    trunk: np.ndarray
    """(P, 3) points from end A to end B (which end is the root is decided later)."""
    trunk_radii: np.ndarray
    """(P,) inscribed radius along the trunk, mm."""
    branches: tuple[Branch, ...]
    n_spurs: int
    """Terminal paths pruned as spurs."""

    @property
    def trunk_arc(self) -> np.ndarray:
        """(P,) arc length along the trunk from end A, mm."""
        return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(self.trunk, axis=0),
                                                               axis=1))])

    def reversed(self) -> Skeleton:
        """The same skeleton with the trunk running from end B to end A."""
        n = len(self.trunk)
        return Skeleton(self.trunk[::-1].copy(), self.trunk_radii[::-1].copy(),
                        tuple(Branch(b.points, b.radii, n - 1 - b.junction_index)
                              for b in self.branches), self.n_spurs)


def _graph(ijk: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edges (E, 2) and lengths (E,) between 26-neighbouring skeleton voxels."""
    from scipy.spatial import cKDTree

    tree = cKDTree(ijk)
    pairs = tree.query_pairs(np.sqrt(3.0) + 1e-6, output_type="ndarray")
    length = np.linalg.norm(ijk[pairs[:, 0]] - ijk[pairs[:, 1]], axis=1) * spacing
    return pairs, length, np.arange(len(ijk))


@dataclass
class SkeletonTree:
    """The pruned centreline tree of a lumen (LPS mm); nodes are skeleton voxels."""

    pos: np.ndarray
    """(N, 3) LPS mm of every skeleton voxel (tree nodes index it)."""
    radius: np.ndarray
    """(N,) inscribed radius, mm."""
    tree: Any
    """networkx.Graph, a tree with edge ``weight`` in mm."""
    leaves: tuple[int, ...]
    """The tree's ends."""
    n_spurs: int

    def end_width(self, leaf: int, skip_mm: float = 5.0, length_mm: float = 25.0) -> float:
        """Median inscribed radius between ``skip_mm`` and ``length_mm`` from an end, mm (the
        first millimetres are skipped: the skeleton of a flat end tapers into it)."""
        import networkx as nx

        dist = nx.single_source_dijkstra_path_length(self.tree, leaf, cutoff=length_mm)
        nodes = [n for n, d in dist.items() if d >= skip_mm] or list(dist)
        return float(np.median(self.radius[nodes]))

    def distances(self, source: int) -> dict[int, float]:
        """Path length from ``source`` to every node, mm."""
        import networkx as nx

        return dict(nx.single_source_dijkstra_path_length(self.tree, source))

    def skeleton(self, a: int, b: int) -> Skeleton:
        """The trunk from end ``a`` to end ``b`` and every other end as a branch."""
        import networkx as nx

        trunk_nodes = nx.shortest_path(self.tree, a, b, weight="weight")
        on_trunk = {n: k for k, n in enumerate(trunk_nodes)}
        branches = []
        for leaf in self.leaves:
            if leaf in (a, b):
                continue
            path = nx.shortest_path(self.tree, leaf, trunk_nodes[0])
            k = next(i for i, n in enumerate(path) if n in on_trunk)
            nodes = path[:k + 1][::-1]
            branches.append(Branch(points=self.pos[nodes], radii=self.radius[nodes],
                                   junction_index=on_trunk[nodes[0]]))
        return Skeleton(trunk=self.pos[trunk_nodes], trunk_radii=self.radius[trunk_nodes],
                        branches=tuple(branches), n_spurs=self.n_spurs)


def skeleton_tree(volume: LabelVolume, spur_mm: float = 8.0) -> SkeletonTree:
    """The pruned centreline tree of ``volume``'s lumen (see the module doc).

    Raises:
        PatientError: a lumen without two ends (e.g. a blob or a ring).
    """
    import networkx as nx
    from scipy.ndimage import distance_transform_edt
    from skimage.morphology import skeletonize

    mask = volume.mask
    h = volume.spacing
    skel = skeletonize(mask)
    ijk = np.argwhere(skel)
    if len(ijk) < 10:
        raise PatientError(f"expected a tubular lumen in {volume.source}, found a skeleton of "
                           f"{len(ijk)} voxels (a blob?)")
    edt = distance_transform_edt(mask, sampling=h)
    radius = edt[tuple(ijk.T)]
    pairs, length, _ = _graph(ijk, h)
    g = nx.Graph()
    g.add_nodes_from(range(len(ijk)))
    g.add_weighted_edges_from((int(a), int(b), float(w))
                              for (a, b), w in zip(pairs, length, strict=True))
    comp = max(nx.connected_components(g), key=len)
    tree = nx.minimum_spanning_tree(g.subgraph(comp))
    n_spurs = 0
    while True:
        leaves = [n for n in tree.nodes if tree.degree(n) == 1]
        removed = False
        for leaf in leaves:
            if leaf not in tree or tree.degree(leaf) != 1:
                continue
            path = [leaf]
            prev, cur = None, leaf
            while True:
                nbrs = [n for n in tree.neighbors(cur) if n != prev]
                if len(nbrs) != 1:
                    break
                prev, cur = cur, nbrs[0]
                path.append(cur)
            if tree.degree(cur) < 3:  # the whole tree is one path: keep it
                continue
            plen = sum(float(tree[a][b]["weight"]) for a, b in itertools.pairwise(path))
            if plen < float(radius[cur]) + spur_mm:
                tree.remove_nodes_from(path[:-1])
                n_spurs += 1
                removed = True
        if not removed:
            break
    leaves = [n for n in tree.nodes if tree.degree(n) == 1]
    if len(leaves) < 2:
        raise PatientError(f"expected a lumen with two ends (root and descending aorta) in "
                           f"{volume.source}, found {len(leaves)}: a closed ring or a blob?")
    return SkeletonTree(pos=volume.points(ijk), radius=np.asarray(radius, dtype=float),
                        tree=tree, leaves=tuple(leaves), n_spurs=n_spurs)
