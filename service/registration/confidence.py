"""How far to trust a frame, without the ground truth.

A frame's displacement u was produced for forces g by some forward model. The exact (discrete)
physics asks ``f_int(u) = g`` on the free nodes; the residual ``r = f_int(u) - g`` says how far u
is from the equilibrium of its own forces, and one solve with the rest stiffness turns it into a
displacement, ``d = K0^-1 r ~ u - u_eq``, the linearised error of u against that equilibrium.
The rest stiffness knows nothing of rotation, and a nearly incompressible body's stiffness
rotated against it is off by about lambda / mu (fifty here): so the residual is taken into the
rest frame node by node (the local rotation of the deformation, as corotational "stiffness
warping" does), solved there, and turned back. Its mean nodal
norm estimates the forward model's error (a network's; the FEM's is its Newton tolerance).

The registration adds its own error: points it could not explain. The cloud's RMS distance to
the registered surface, beyond the noise the session declared (in quadrature: the two are
independent), measures it where the camera looks; a calibrated factor turns it into a mean over
the nodes (MISFIT_FACTOR).

A fit can be exact and still wrong: the cloud may not determine the forces. The third term
is what the inverse problem leaves open, linearised at the frame's answer with H = C^T A C +
alpha I the Gauss-Newton Hessian (levenberg.py's notation), B = C H^-1 C^T = M (A M + alpha
I)^-1, M = C C^T (r x r algebra at the frame's Jacobian), in quadrature, RMS over the whole
surface, which moves more than the interior (not the objective's nodes, U's rows: a few matched
triangles far from the tool barely move under the forces they leave open, and their RMS read a
fifth of the error over the nodes):
- the prior's pull: alpha (|g|^2's weight) pulls the forces towards zero by alpha H^-1 g, a bias
  the truth does not have. In a direction the cloud does not see (one point, a view away from
  the tool, a pull that slides the seen surface along itself), the answer keeps none of the
  truth's force, and the pull at the answer's own g is nil. So the pull is also taken on a
  force prior, the model's largest tool force (max_force: the scene's, from the store) along
  each axis, spread over the support, and the larger of the two counts;
- the step left: H^-1 grad at the answer, the Gauss-Newton step to the optimum (an optimiser
  stopped by its tolerance in a flat direction can be far from it);
- the declared noise sigma, which no misfit shows (a fit inside the noise can still be off):
  the points' noise moves the coefficients by dc = -C H^-1 C^T N^T W eps, covariance sigma^2 B
  (N^T W^2 N) B^T.
The network's Jacobian is low-rank, the Newton method's dense (C the identity). With noise
declared they are taken at the answer (the Newton method's: 3 solves per support node, unless
its last step formed it there); without, at rest, kept per operator (FEMOperator.estimate_jacobian).
"""

from __future__ import annotations

import functools
import math
import threading

import numpy as np

from ..fem.assembly import Assembler
from ..fem.material import NeoHookean
from ..fem.rest import rest_compliance
from ..jit import kernels
from ..mesh import TetMesh
from ..spare import Beside
from .distance import Match
from .levenberg import distance_gram

Array = np.ndarray

_CACHE_KEY = "_elastreg_residual_estimator"
_CACHE_LOCK = threading.Lock()


class ResidualEstimator:
    """The forward error of a displacement from its Neo-Hookean residual (see the module)."""

    def __init__(self, mesh: TetMesh, material: NeoHookean, backend: str | None = None) -> None:
        self.mesh = mesh
        self.assembler = Assembler(mesh, material)
        # single precision: an estimate needs a few digits, and float32 halves the solve
        self._rest = rest_compliance(mesh, material, backend, single=True)
        self._scatter = tet_to_node(mesh)

    def correction(self, u: Array, forces: Array, support: Array) -> Array:
        """d = R K0^-1 R^T (f_int(u) - g) ~ u - u_eq(g): the linearised error of u, with each
        node's residual turned into the rest frame and back (R: the nodes' rotations).

        Shape: u (n, 3), forces (k, 3) on support (k,) -> (n, 3), zero on fixed nodes.
        """
        # the rotations on a spare core while the internal force is assembled: both read u only
        rotations = Beside(functools.partial(node_rotations, self.assembler, u, scatter=self._scatter))
        f = self.assembler.internal_force(u)
        R = rotations.result()
        np.subtract.at(f, support, forces)
        if not np.isfinite(f).all():
            return np.full_like(u, np.inf)
        r = self.assembler.pack(np.einsum("nji,nj->ni", R, f))  # into the rest frame: R^T f
        d = self._rest.solve_free(r)
        return np.einsum("nij,nj->ni", R, self.assembler.unpack(d))  # and back

    def forward_error(self, u: Array, forces: Array, support: Array) -> float:
        """Mean nodal norm of :meth:`correction` (length units of the mesh)."""
        d = self.correction(u, forces, support)
        return float(np.linalg.norm(d, axis=1).mean())


def estimator_for(model) -> ResidualEstimator:
    """The model's estimator, made on first use and kept on the (immutable, shared) model."""
    est = model.__dict__.get(_CACHE_KEY)
    if est is None:
        with _CACHE_LOCK:
            est = model.__dict__.get(_CACHE_KEY)
            if est is None:
                backend = getattr(getattr(model, "options", None), "backend", None)
                est = ResidualEstimator(model.mesh, model.material, backend)
                model.__dict__[_CACHE_KEY] = est
    return est


#: the misfit is a distance along the seen surface's normal, the error a mean over every node,
#: seen or not: on the Newton method's frames (nil forward error) the error was 4.4x the misfit
#: (median) and at most 4.9x in nine frames of ten, at phantom tool sites that the anysite
#: benchmark never uses (benchmarks/calibrate_estimate.py, reports/anysite/calibration.json)
MISFIT_FACTOR = 4.9


#: a session's support is a tool's patch with its margin: up to this many tool patches' nodes
#: (the any-site part's and the demo's supports are three times their tool's patch)
SUPPORT_MARGIN = 3


def prior_windows(points: Array, tool_patch: int | None) -> list[Array]:
    """Where the force prior puts a tool's force (:func:`force_prior`): the whole support (k
    nodes at `points`, (k, 3)) where it is at most SUPPORT_MARGIN tool patches, else windows of
    that many nodes, ceil(k / window) of them, each the nodes nearest a centre, the centres
    spread by farthest-point sampling. Spread evenly over a support of hundreds of nodes, one
    tool's force is a diffuse pull the far side of a view barely feels (the Newton method on
    the phantom's 592-node region, views away from the tool: 3 frames in 15 under half their
    error; windows: none). Positions into the support."""
    k = len(points)
    window = None if tool_patch is None else SUPPORT_MARGIN * int(tool_patch)
    if window is None or k <= window:
        return [np.arange(k)]
    centres = [0]
    d = np.linalg.norm(points - points[0], axis=1)
    for _ in range(math.ceil(k / window) - 1):
        centres.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(points - points[centres[-1]], axis=1))
    return [np.sort(np.argsort(np.linalg.norm(points - points[c], axis=1))[:window]) for c in centres]


#: a load may pass the scene's max_force by this share and still be within training: the sum of
#: nodal magnitudes rounds (1 N on 20 phantom nodes sums to 1 + 2e-16; a float32 body to 1 + 1.5e-8)
LOAD_ROUNDING = 1e-6


def past_max_force(load: float, max_force: float | None) -> bool:
    """Whether a load (N) passes the model's largest tool force, rounding allowed; False without one."""
    return max_force is not None and load > max_force * (1 + LOAD_ROUNDING)


def beyond_training(forces: Array, max_force: float | None) -> bool:
    """Whether nodal forces (k, 3) load the model past its largest tool force, measured as the
    trainer measures a sample's load (the sum of nodal magnitudes); False without one."""
    return past_max_force(float(np.linalg.norm(forces, axis=1).sum()), max_force)


def force_prior(jac, windows: list[Array], k: int, max_force: float) -> Array:
    """L (r, 3 w) with L L^T the prior the module's third term takes on the basis coefficients
    a tool's force gives, three columns per window (:func:`prior_windows`): one total force,
    spread evenly over the window's nodes, of the model's largest (`max_force`) along each axis.
    A bound, not a mean: the estimate must not be small where the error is large, and a tool
    pulls in any one direction as hard as in all three (inverse_spread takes the worst window).
    `jac` a Jacobian at the frame's forces (C's products) on a support of k nodes."""
    columns = []
    for nodes in windows:
        for axis in range(3):
            e = np.zeros((k, 3))
            e[nodes, axis] = float(max_force) / len(nodes)
            columns.append(np.asarray(jac.matvec(e.ravel()), np.float64))
    return np.column_stack(columns)


def inverse_spread(
    jac,
    match: Match,
    faces: Array,
    alpha: float,
    noise: float,
    readout_gram: Array,
    Cg: Array,
    prior: Array | None = None,
    readout_nodes: int | None = None,
) -> tuple[float, float]:
    """What the cloud leaves uncertain in the displacement (see the module): the declared
    `noise`'s spread, and the prior's pull alpha (C^T A C + alpha I)^-1 c towards zero force,
    which the truth does not have, on c = C g (the answer's: the pull it had) or, where larger,
    in mean square over the force `prior` (:func:`force_prior`'s L: where the cloud does not
    determine a direction, the answer keeps none of the truth's force in it); in quadrature,
    RMS over the readout's nodes; and the Gauss-Newton step left to the optimum. With noise,
    gamma = tr((C^T A C + alpha I)^-1 C^T A C), the force directions the cloud determines
    (noise_prior's rule; NaN without: the r x r products it needs are skipped). `jac` a
    low-rank Jacobian with ``gram()`` at the frame's forces g, `Cg` its image C g (r,), `match`
    the distance's at its positions, `readout_gram` (r, r) float64 the Gram of the readout
    du/dc over `readout_nodes` nodes (jac.U's rows and the rest of the surface's; None: jac.U's
    alone, U^T U). Returns (spread, gamma)."""
    Nw, A = distance_gram(jac.U, match, faces)  # in U's precision, as the LM model's
    w = np.asarray(match.weight, np.float64)
    # M A as the Gauss-Newton model forms it (no product with the Newton method's identity M);
    # a C-ordered copy, since alpha goes on its diagonal
    X = np.array(jac.gram_product(A), np.float64, order="C")
    lin = max(alpha, precision_floor(X, jac.U.dtype))  # the alpha the model is linearised at
    X.flat[:: len(A) + 1] += lin
    r = len(A)
    # the objective's gradient through C: C grad = C C^T N^T W d + alpha C g (d: the distances)
    Cg = np.asarray(Cg, np.float64)
    b = np.asarray(Nw.T @ (np.sqrt(w) * np.linalg.norm(match.r, axis=0)).astype(Nw.dtype), np.float64)
    grad = jac.matvec(jac.rmatvec(b)) + alpha * Cg
    # the prior's pulls alpha X^-1 (C g, L), the step left, and (for the noise) B^T = X^-1 M: one solve
    L = np.zeros((r, 0)) if prior is None else np.asarray(prior, np.float64)
    M = np.asarray(jac.gram(), np.float64) if noise else np.zeros((r, 0))
    sol = np.linalg.solve(X, np.column_stack([Cg, grad, L, M]))
    pull, left, prior_pull, Bt = (
        lin * sol[:, 0],
        sol[:, 1],
        lin * sol[:, 2 : 2 + L.shape[1]],
        sol[:, 2 + L.shape[1] :],
    )
    p = jac.U.shape[0] // 3 if readout_nodes is None else int(readout_nodes)
    # the prior's columns come in threes, a tool force along each axis per window: the worst window
    per_window = np.sum(prior_pull * (readout_gram @ prior_pull), axis=0).reshape(-1, 3).sum(axis=1)
    bias2 = max(float(pull @ (readout_gram @ pull)), float(per_window.max(initial=0.0)), 0.0)
    step2 = max(float(left @ (readout_gram @ left)), 0.0)
    if not noise:
        return math.sqrt((bias2 + step2) / p), math.nan
    if w.size and w.min() == w.max():  # the squared loss: one weight, N^T W^2 N = w A
        A2 = w[0] * A
    else:
        A2 = (Nw.T @ (Nw * w[:, None].astype(Nw.dtype))).astype(np.float64)
    cov = Bt.T @ (A2 @ Bt)  # of the coefficients, per unit noise variance
    spread2 = float(noise) ** 2 * max(float(np.sum(cov * readout_gram)), 0.0)
    gamma = float(np.sum(Bt * A.T))  # tr(X^-1 M A): C^T A C's eigenvalues l, sum of l / (l + alpha)
    return math.sqrt((spread2 + bias2 + step2) / p), gamma


def precision_floor(MA: Array, dtype) -> float:
    """The least alpha inverse_spread linearises at: MA (r, r), formed in U's precision `dtype`
    (A's rows, the network's float32 C), is known to eps x its largest eigenvalue; below that a
    solve divides rounding by alpha (the phantom network at 1e-15: a 0.27 mm frame estimated
    5.3 m, through the step left in directions no force reaches). A larger alpha only enlarges
    the prior's pulls, alpha (l + alpha)^-1 on each eigenvalue l, so the estimate errs high. The
    trace bounds the largest eigenvalue in O(r) (eigvals: 12 ms at the phantom's r = 192)."""
    return float(np.finfo(dtype).eps) * max(float(np.trace(MA)), 0.0)


def error_estimate(forward_error: float, distance_rms: float, noise: float | None, spread: float = 0.0) -> float:
    """The frame's estimate: forward error plus the misfit the declared noise does not explain,
    scaled to a mean over the nodes (MISFIT_FACTOR), plus the inverse problem's `spread` (:func:`inverse_spread`).
    Noise and misfit are independent, so they add in quadrature: subtracting the noise from the
    RMS instead hid a 0.3 mm misfit under 0.5 mm of noise (the demo's frames with their noise
    declared: estimates a third of the error)."""
    noise = noise or 0.0
    unexplained = math.sqrt(max(float(distance_rms) ** 2 - noise * noise, 0.0))
    if not (np.isfinite(forward_error) and np.isfinite(unexplained) and np.isfinite(spread)):
        return float("inf")
    return float(forward_error + MISFIT_FACTOR * unexplained + spread)


def node_rotations(assembler: Assembler, u: Array, iterations: int = 6, scatter=None) -> Array:
    """Each node's rotation: the polar factor of the volume-weighted sum of its tets'
    deformation gradients (Newton's iteration X <- (X + X^-T) / 2, from X scaled to unit
    determinant). `scatter`: :func:`tet_to_node` of the mesh, if kept (the NumPy path's).
    One compiled pass over tets and nodes where numba imports (0.3 ms on the paper's liver,
    against 5 ms for the NumPy path). Shape: u (n, 3) -> (n, 3, 3)."""
    mesh = assembler.mesh
    K = _compiled()
    if K is not None:
        out = np.zeros((mesh.n_nodes, 3, 3))
        K._rotations_loop(np.ascontiguousarray(u, np.float64), mesh.tets, mesh.shape_gradients, mesh.volumes,
                          iterations, out)  # fmt: skip
        return out
    scatter = tet_to_node(mesh) if scatter is None else scatter
    weighted = (assembler.F(u) * mesh.volumes[:, None, None]).reshape(-1, 9)  # (t, 9)
    X: Array = np.asarray(scatter @ weighted, np.float64).reshape(-1, 3, 3)
    det = np.linalg.det(X)
    X[~(det > 0)] = np.eye(3)  # a node whose tets average to a fold: no rotation to undo
    X /= np.cbrt(np.where(det > 0, det, 1.0))[:, None, None]  # scale out the volume: same factor
    for _ in range(iterations):
        X = 0.5 * (X + _inverse_transpose(X))
    return X


def _rotations_loop(u, tets, grads, vols, iterations, out):
    """node_rotations' loops: sum vol F into each tet's nodes (out zeroed), then the polar
    iteration node by node, in place."""
    F = np.empty((3, 3))
    for t in range(tets.shape[0]):
        F[:] = 0.0
        for a in range(4):
            na = tets[t, a]
            for i in range(3):
                for j in range(3):
                    F[i, j] += u[na, i] * grads[t, a, j]
        for i in range(3):
            F[i, i] += 1.0
        v = vols[t]
        for a in range(4):
            na = tets[t, a]
            for i in range(3):
                for j in range(3):
                    out[na, i, j] += v * F[i, j]
    C = np.empty((3, 3))
    for n in range(out.shape[0]):
        X = out[n]
        det = (X[0, 0] * (X[1, 1] * X[2, 2] - X[1, 2] * X[2, 1]) - X[0, 1] * (X[1, 0] * X[2, 2] - X[1, 2] * X[2, 0])
               + X[0, 2] * (X[1, 0] * X[2, 1] - X[1, 1] * X[2, 0]))  # fmt: skip
        if not det > 0:  # a fold (or a node with no tets): no rotation to undo
            for i in range(3):
                for j in range(3):
                    X[i, j] = 1.0 if i == j else 0.0
            continue
        s = det ** (-1.0 / 3.0)
        for i in range(3):
            for j in range(3):
                X[i, j] *= s
        for _ in range(iterations):
            # cofactors: rows r1 x r2, r2 x r0, r0 x r1; X^-T = C / det
            for i in range(3):
                i1, i2 = (i + 1) % 3, (i + 2) % 3
                C[i, 0] = X[i1, 1] * X[i2, 2] - X[i1, 2] * X[i2, 1]
                C[i, 1] = X[i1, 2] * X[i2, 0] - X[i1, 0] * X[i2, 2]
                C[i, 2] = X[i1, 0] * X[i2, 1] - X[i1, 1] * X[i2, 0]
            d = X[0, 0] * C[0, 0] + X[0, 1] * C[0, 1] + X[0, 2] * C[0, 2]
            for i in range(3):
                for j in range(3):
                    X[i, j] = 0.5 * (X[i, j] + C[i, j] / d)


_compiled = kernels(_rotations_loop)  # the loops compiled (numba), or None


def tet_to_node(mesh: TetMesh):
    """The sparse (n, t) sum of each tet's value into its four nodes."""
    import scipy.sparse as sp

    tets = np.arange(mesh.n_tets).repeat(4)
    return sp.csr_matrix((np.ones(tets.size), (mesh.tets.ravel(), tets)), shape=(mesh.n_nodes, mesh.n_tets))


def _inverse_transpose(X: Array) -> Array:
    """X^-T of (n, 3, 3) matrices by cofactors (a batched inverse costs several times more)."""
    r0, r1, r2 = X[:, 0], X[:, 1], X[:, 2]
    C = np.stack([np.cross(r1, r2), np.cross(r2, r0), np.cross(r0, r1)], axis=1)
    return C / np.einsum("ni,ni->n", r0, C[:, 0])[:, None, None]
