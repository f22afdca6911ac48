"""The rest compliance (fem/rest.py): K0^-1 on full vectors, one factorisation per mesh and material."""

import numpy as np

from service.fem.assembly import Assembler
from service.fem.material import NeoHookean
from service.fem.rest import rest_compliance

MAT = NeoHookean(4500.0, 0.45)


def test_the_response_solves_the_rest_stiffness_and_fixed_nodes_stay(bar):
    asm = Assembler(bar, MAT)
    nodes = bar.free_surface_nodes[:4]
    G = rest_compliance(bar, MAT).response(nodes)
    K = asm.stiffness_at_rest().toarray()
    for col in (0, 5, 11):
        f = np.zeros(3 * bar.n_nodes)
        f[3 * nodes[col // 3] + col % 3] = 1.0
        u = asm.unpack(np.linalg.solve(K, f[bar.free_dofs])).ravel()
        np.testing.assert_allclose(G[:, col], u, atol=1e-10 * np.abs(u).max())
    assert not G.reshape(bar.n_nodes, 3, -1)[bar.fixed].any()


def test_a_batch_of_loads_is_the_response_times_the_forces(bar):
    comp = rest_compliance(bar, MAT)
    nodes = bar.free_surface_nodes[3:9]
    forces = np.random.default_rng(0).normal(size=(5, nodes.size, 3))
    U = comp.displacements(forces, nodes)
    np.testing.assert_allclose(U, forces.reshape(5, -1) @ comp.response(nodes).T, rtol=1e-9, atol=1e-15)
    rhs = np.random.default_rng(1).normal(size=(3 * bar.n_nodes, 7))
    np.testing.assert_allclose(comp.solve(rhs, chunk=2), comp.solve(rhs), rtol=1e-10, atol=1e-16)


def test_one_factorisation_per_mesh_and_material(bar):
    assert rest_compliance(bar, MAT) is rest_compliance(bar, NeoHookean(4500.0, 0.45))
    assert rest_compliance(bar, MAT) is not rest_compliance(bar, MAT.with_stiffness(9000.0))
