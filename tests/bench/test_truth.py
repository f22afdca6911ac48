"""The finer mesh that the anysite part's truth comes from."""

import numpy as np
import pytest

from service.bench.anysite import anysite_cases, peak_for_reach, spread_sites
from service.bench.truth import coarse_edges, fine_patch, subdivide, traction_shares


def test_subdivision_keeps_the_body_and_its_nodes(bar):
    fine = subdivide(bar)
    edges = coarse_edges(bar)
    assert fine.n_tets == 8 * bar.n_tets and fine.n_nodes == bar.n_nodes + len(edges)
    np.testing.assert_array_equal(fine.nodes[: bar.n_nodes], bar.nodes)  # coarse ids unchanged
    np.testing.assert_allclose(fine.nodes[bar.n_nodes :], bar.nodes[edges].mean(axis=1))
    assert np.isclose(fine.volumes.sum(), bar.volumes.sum(), rtol=1e-12) and (fine.volumes > 0).all()
    # children of one tet are not all alike: the octahedron's four are smaller than a corner's
    assert fine.volumes.max() / fine.volumes.min() < 10
    # the Dirichlet surface is the same surface: fixed coarse nodes and the midpoints between them
    fixed = np.zeros(bar.n_nodes, bool)
    fixed[bar.fixed] = True
    want = np.concatenate([bar.fixed, bar.n_nodes + np.flatnonzero(fixed[edges].all(axis=1))])
    np.testing.assert_array_equal(fine.fixed, np.sort(want))
    # the boundary is the same surface, with four times the triangles
    assert len(fine.surface_faces) == 4 * len(bar.surface_faces)


def test_a_patch_on_the_fine_mesh_covers_its_area(bar):
    fine = subdivide(bar)
    site = int(bar.free_surface_nodes[0])
    tool = bar.surface_patch(site, 6)
    patch = fine_patch(bar, fine, tool)
    assert set(tool) <= set(patch.tolist()) and len(patch) > len(tool)
    assert np.isin(patch, fine.surface_nodes).all()
    ends = coarse_edges(bar)[patch[patch >= bar.n_nodes] - bar.n_nodes]
    assert np.isin(ends, tool).all()  # every midpoint between two of the patch's nodes


def test_sites_spread_over_the_region(bar):
    region = bar.free_surface_nodes
    sites = spread_sites(bar, region, 4, np.random.default_rng(0))
    assert len(set(sites.tolist())) == 4 and np.isin(sites, region).all()
    x = bar.nodes[sites]
    gaps = np.linalg.norm(x[:, None] - x[None], axis=2)[np.triu_indices(4, 1)]
    assert gaps.min() > 0.2 * np.ptp(bar.nodes[region], axis=0).max()


def test_a_site_is_named_by_how_far_its_tool_moves_the_organ(entry):
    """The issue's loads move the organ 3-7 cm: each any-site case's name says its reach, the
    largest nodal displacement of its truth over its frames, so a report shows which sites
    are in that range."""
    case = anysite_cases(entry, sites=1, frames=2)[0]
    reach = 1e3 * np.linalg.norm(case.positions - entry.mesh.nodes, axis=2).max()
    assert reach > 0 and case.name.endswith(f", {reach:.0f} mm)")


def test_a_sites_load_aims_at_its_reach_within_the_force_range(entry):
    """The peak force whose linear response moves the organ `reach` at most, unless the
    model's force range (a quarter of its trained maximum to all of it) says otherwise."""
    from service.fem.rest import RestCompliance

    fine = subdivide(entry.mesh)
    compliance = RestCompliance(fine, entry.fem.material)
    site = int(entry.mesh.free_surface_nodes[-1])
    patch = fine_patch(entry.mesh, fine, entry.mesh.surface_patch(site, 6))
    g = np.zeros((fine.n_nodes, 3))
    g[patch] = fine.patch_normal(patch) / patch.size  # 1 N in all, as make_sequence pulls
    per_newton = np.linalg.norm(compliance.solve(g.ravel()).reshape(-1, 3), axis=1).max()
    aimed = 0.05 / per_newton
    assert peak_for_reach(compliance, patch, 0.05, max_force=2 * aimed) == pytest.approx(aimed, rel=1e-9)
    assert peak_for_reach(compliance, patch, 0.05, max_force=0.5 * aimed) == pytest.approx(0.5 * aimed)
    assert peak_for_reach(compliance, patch, 0.05, max_force=8 * aimed) == pytest.approx(2 * aimed)


def test_a_uniform_traction_on_ten_node_tets_loads_the_patch_midpoints(bar):
    """Corners of a straight six-node triangle take none of a uniform traction, each edge
    midpoint a third of the triangle's force; the shares cover the patch's triangles' area."""
    fine = subdivide(bar)
    tool = bar.surface_patch(int(bar.free_surface_nodes[0]), 9)
    spread = fine_patch(bar, fine, tool)
    shares = traction_shares(bar, fine, tool, spread)
    assert shares.sum() == pytest.approx(1.0) and (shares >= 0).all()
    assert not shares[spread < bar.n_nodes].any() and shares[spread >= bar.n_nodes].any()


def test_a_quadratic_truth_scores_the_same_loads_on_ten_node_tets(entry):
    """The same site, peak and turn as the subdivided truth, the same net force; another
    discretisation's answer on the same nodes, softer (linear tets lock at nu = 0.49)."""
    [linear] = anysite_cases(entry, sites=1, frames=2)
    [quadratic] = anysite_cases(entry, sites=1, frames=2, truth="quadratic")
    np.testing.assert_allclose(quadratic.net_forces, linear.net_forces, rtol=1e-9, atol=1e-12)
    moved = [np.linalg.norm(c.positions - entry.mesh.nodes, axis=2).max() for c in (linear, quadratic)]
    assert moved[1] > 1.05 * moved[0]
    with pytest.raises(ValueError, match="unknown truth"):
        anysite_cases(entry, sites=1, frames=2, truth="cubic")
