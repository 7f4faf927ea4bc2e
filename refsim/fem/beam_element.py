"""Pure local kernels of the co-rotational Timoshenko beam element (2 nodes, 6 DoFs per node).

Everything here is batched over elements (leading axis ``m``) and knows nothing about meshes or assembly;
:mod:`refsim.fem.needle` assembles these kernels.

Element stiffness
-----------------
The closed-form 12×12 Timoshenko stiffness of a straight prismatic beam (Przemieniecki, *Theory of Matrix
Structural Analysis*, 1968, §5.6), with the shear parameter Φ = 12 E I / (κ G A L²). It is the exact static
condensation of the continuous Timoshenko beam onto its end DoFs, so a cantilever under a tip load is exact at
any element count. scikit-fem has no Timoshenko line element with interdependent interpolation; the closed
form
is therefore used here, and ``tests/fem/test_beam_element.py`` cross-checks its bending block against a
scikit-fem assembly of the same energy (P1 deflection and rotation, one-point reduced integration of the shear
term, refined and condensed onto the end DoFs), which converges to it at second order.

Local DoF order: ``[u_a, v_a, w_a, θx_a, θy_a, θz_a, u_b, v_b, w_b, θx_b, θy_b, θz_b]`` in the element frame
(axis 0 along the beam). Bending in the x–y plane couples (v, θz), in the x–z plane (w, θy) with v' = θz and
w' = −θy.

Co-rotational kinematics
------------------------
The element frame R_e = [e1, e2, e3] (columns, world coordinates) follows Crisfield (1990) and Battini &
Pacoste (2002): e1 is the chord from node a to node b, e3 = e1 × q / ‖e1 × q‖ with q the mean of the two
nodes' second material axes, e2 = e3 × e1. The local deformations are the elongation ū = l − l₀ and the nodal
rotations relative to the element frame, θ̄ = log(R_eᵀ Q) (Q the nodal frame; the rest pose is straight, so
R_e and Q are equal at rest). The local transverse displacements vanish by construction. The strain energy is
U = ½ dᵀ K₇ d with d = [ū, θ̄_a, θ̄_b] (7,) and K₇ the corresponding block of the 12×12 stiffness.

Variations use world-frame (spatial) rotation increments δθ, Q ← exp(δθ) Q. With the element spin
δw = R_e (w₁, w₂, w₃):

    w₂ = e3·(δx_a − δx_b)/l,   w₃ = e2·(δx_b − δx_a)/l,
    w₁ = (q₁/q₂) w₂ + [δθ_a·(q_a × e3) + δθ_b·(q_b × e3)] / (2 q₂),   (q₁, q₂) = (q·e1, q·e2),
    δθ̄ = J_l(θ̄)⁻¹ R_eᵀ (δθ − δw),   δū = e1·(δx_b − δx_a),

J_l the left Jacobian of SO(3). This gives B = ∂d/∂p (7×12) and the consistent internal force f = Bᵀ K₇ d.
"""

from __future__ import annotations

import numpy as np

from refsim.fem import needle_kernels
from refsim.geometry.rotations import rotation_vector, skew

__all__ = [
    "LOCAL_REDUCED_DOFS",
    "timoshenko_stiffness",
    "left_jacobian_inverse",
    "corotational_frames",
    "corotational_frames_reference",
    "local_deformations",
    "local_deformations_reference",
    "beam_element_forces",
    "beam_element_forces_reference",
    "hermite_shapes",
]

# Positions of d = [ū, θ̄_a, θ̄_b] in the 12 local DoFs (ū is u_b with u_a = 0).
LOCAL_REDUCED_DOFS = np.array([6, 3, 4, 5, 9, 10, 11])

# Below this angle [rad] the series of the inverse left Jacobian's K² coefficient (1/12 + θ²/720) is used;
# its truncation error θ⁴/30240 is then below 1e-20.
_SMALL_ANGLE = 1e-4


def timoshenko_stiffness(
    length: np.ndarray | float,
    *,
    youngs_modulus: float,
    shear_modulus: float,
    area: float,
    second_moment: float,
    polar_moment: float,
    shear_coefficient: float,
) -> np.ndarray:
    """Closed-form 12×12 Timoshenko beam stiffness in the local frame (Przemieniecki 1968).

    Parameters
    ----------
    length : Element rest lengths L [m], scalar or shape (m,), > 0.
    youngs_modulus : E [Pa].
    shear_modulus : G [Pa].
    area : Cross-section area A [m²].
    second_moment : Second moment of area I about either transverse axis [m⁴] (circular section).
    polar_moment : Torsion constant J [m⁴].
    shear_coefficient : Shear correction factor κ [-].

    Returns
    -------
    Stiffness [N/m, N, N·m] in the local DoF order of the module, shape (12, 12) or (m, 12, 12).
    """
    lengths = np.atleast_1d(np.asarray(length, dtype=float))
    phi = 12.0 * youngs_modulus * second_moment / (shear_coefficient * shear_modulus * area * lengths**2)
    out = np.zeros((lengths.size, 12, 12))
    axial = youngs_modulus * area / lengths
    torsion = shear_modulus * polar_moment / lengths
    for (i, j), value in {(0, 6): axial, (3, 9): torsion}.items():
        out[:, i, i] = out[:, j, j] = value
        out[:, i, j] = out[:, j, i] = -value
    c = youngs_modulus * second_moment / (lengths**3 * (1.0 + phi))
    block = np.empty((lengths.size, 4, 4))
    ln = lengths
    block[:, 0] = np.stack([12 + 0 * ln, 6 * ln, -12 + 0 * ln, 6 * ln], axis=-1)
    block[:, 1] = np.stack([6 * ln, (4 + phi) * ln**2, -6 * ln, (2 - phi) * ln**2], axis=-1)
    block[:, 2] = -block[:, 0]
    block[:, 3] = np.stack([6 * ln, (2 - phi) * ln**2, -6 * ln, (4 + phi) * ln**2], axis=-1)
    block *= c[:, None, None]
    # x–y plane: (v, θz) with v' = θz; x–z plane: (w, θy) with w' = −θy, i.e. the same block with θ → −θ.
    xy = np.array([1, 5, 7, 11])
    xz = np.array([2, 4, 8, 10])
    flip = np.array([1.0, -1.0, 1.0, -1.0])
    out[:, xy[:, None], xy[None, :]] = block
    out[:, xz[:, None], xz[None, :]] = block * flip[:, None] * flip[None, :]
    return out[0] if np.ndim(length) == 0 else out


def left_jacobian_inverse(rotation_vectors: np.ndarray) -> np.ndarray:
    """Inverse left Jacobian of SO(3): δθ = J_l(θ)⁻¹ ω when δR Rᵀ = skew(ω), R = exp(θ).

    J_l⁻¹ = I − ½ K + (1/θ² − (1 + cos θ)/(2 θ sin θ)) K², K = skew(θ), series near θ = 0.

    Parameters
    ----------
    rotation_vectors : θ [rad], shape (k, 3), ‖θ‖ < π.

    Returns
    -------
    Matrices, shape (k, 3, 3).
    """
    theta = np.linalg.norm(rotation_vectors, axis=-1)
    small = theta < _SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    coefficient = np.where(
        small,
        1.0 / 12.0 + theta**2 / 720.0,
        1.0 / safe**2 - (1.0 + np.cos(safe)) / (2.0 * safe * np.sin(safe)),
    )
    k = skew(rotation_vectors)
    return np.eye(3) - 0.5 * k + coefficient[:, None, None] * (k @ k)


def corotational_frames(
    positions_a: np.ndarray, positions_b: np.ndarray, frames_a: np.ndarray, frames_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Co-rotational element frames (Crisfield 1990; Battini & Pacoste 2002); a compiled kernel
    (:mod:`refsim.fem.needle_kernels`) with the bits of :func:`corotational_frames_reference`.

    Parameters
    ----------
    positions_a, positions_b : End node positions [m], shape (m, 3).
    frames_a, frames_b : End node frames (columns = material axes, world coordinates), shape (m, 3, 3).

    Returns
    -------
    element_frames : R_e = [e1, e2, e3] as columns, shape (m, 3, 3).
    chord_lengths : Current lengths l [m], shape (m,).
    mean_axes : q = ½ (Q_a[:, 1] + Q_b[:, 1]), shape (m, 3).
    """
    if not _element_shapes(positions_a, positions_b, frames_a, frames_b):
        return corotational_frames_reference(positions_a, positions_b, frames_a, frames_b)
    frames, lengths, mean, status = needle_kernels.element_frames(
        positions_a, positions_b, frames_a, frames_b
    )
    if status:
        # a degenerate element: the NumPy code raises its error
        return corotational_frames_reference(positions_a, positions_b, frames_a, frames_b)
    return frames, lengths, mean


def _element_shapes(positions_a, positions_b, frames_a, frames_b, rest_lengths=None) -> bool:
    """Whether the arguments are the kernels' (m, 3) and (m, 3, 3) float arrays (else the NumPy code runs)."""
    try:
        m = positions_a.shape[0]
        shapes = positions_a.shape == positions_b.shape == (m, 3) and frames_a.shape == frames_b.shape == (
            m,
            3,
            3,
        )
        floats = positions_a.dtype == positions_b.dtype == frames_a.dtype == frames_b.dtype == np.float64
    except (AttributeError, IndexError):
        return False
    return m >= 1 and shapes and floats and (rest_lengths is None or np.shape(rest_lengths) in ((m,), ()))


def corotational_frames_reference(
    positions_a: np.ndarray, positions_b: np.ndarray, frames_a: np.ndarray, frames_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Co-rotational element frames (Crisfield 1990; Battini & Pacoste 2002), in NumPy: the reference of
    :func:`corotational_frames`' compiled kernel.

    Parameters
    ----------
    positions_a, positions_b : End node positions [m], shape (m, 3).
    frames_a, frames_b : End node frames (columns = material axes, world coordinates), shape (m, 3, 3).

    Returns
    -------
    element_frames : R_e = [e1, e2, e3] as columns, shape (m, 3, 3).
    chord_lengths : Current lengths l [m], shape (m,).
    mean_axes : q = ½ (Q_a[:, 1] + Q_b[:, 1]), shape (m, 3).
    """
    chord = positions_b - positions_a
    chord_lengths = np.linalg.norm(chord, axis=-1)
    if np.any(chord_lengths <= 0.0):
        raise ValueError("a beam element has zero length (coincident nodes)")
    e1 = chord / chord_lengths[:, None]
    mean_axes = 0.5 * (frames_a[:, :, 1] + frames_b[:, :, 1])
    e3 = np.cross(e1, mean_axes)
    norm3 = np.linalg.norm(e3, axis=-1)
    if np.any(norm3 <= 1e-12 * np.linalg.norm(mean_axes, axis=-1)):
        raise ValueError("a beam element's chord is parallel to its mean cross-section axis: frame undefined")
    e3 /= norm3[:, None]
    e2 = np.cross(e3, e1)
    return np.stack([e1, e2, e3], axis=-1), chord_lengths, mean_axes


def local_deformations(
    positions_a: np.ndarray,
    positions_b: np.ndarray,
    frames_a: np.ndarray,
    frames_b: np.ndarray,
    rest_lengths: np.ndarray,
) -> dict[str, np.ndarray]:
    """Local deformations d = [ū, θ̄_a, θ̄_b] and their derivative B with respect to the 12 element DoFs.

    Element DoFs p = [x_a (3), θ_a (3), x_b (3), θ_b (3)], rotations as world-frame increments. Compiled
    kernels (:mod:`refsim.fem.needle_kernels`) with the bits of :func:`local_deformations_reference`, which
    answers for a relative rotation within 1e-3 rad of π and raises for a degenerate element.

    Parameters
    ----------
    positions_a, positions_b : End node positions [m], shape (m, 3).
    frames_a, frames_b : End node frames, shape (m, 3, 3).
    rest_lengths : Rest lengths l₀ [m], shape (m,).

    Returns
    -------
    Dictionary with ``deformations`` d [m, rad] (m, 7); ``jacobian`` B = ∂d/∂p (m, 7, 12); ``element_frames``
    R_e (m, 3, 3); ``chord_lengths`` l [m] (m,); ``spin_jacobian`` W = ∂(w₁, w₂, w₃)/∂p (m, 3, 12), the
    element frame's spin in its own axes.
    """
    found = None
    if _element_shapes(positions_a, positions_b, frames_a, frames_b, rest_lengths):
        found = needle_kernels.element_kinematics(positions_a, positions_b, frames_a, frames_b, rest_lengths)
    if found is None:
        return local_deformations_reference(positions_a, positions_b, frames_a, frames_b, rest_lengths)
    return found


def local_deformations_reference(
    positions_a: np.ndarray,
    positions_b: np.ndarray,
    frames_a: np.ndarray,
    frames_b: np.ndarray,
    rest_lengths: np.ndarray,
) -> dict[str, np.ndarray]:
    """Local deformations d = [ū, θ̄_a, θ̄_b] and their derivative B with respect to the 12 element DoFs, in
    NumPy: the reference of :func:`local_deformations`' compiled kernels (and their answer near θ̄ = π).

    Element DoFs p = [x_a (3), θ_a (3), x_b (3), θ_b (3)], rotations as world-frame increments.

    Parameters
    ----------
    positions_a, positions_b : End node positions [m], shape (m, 3).
    frames_a, frames_b : End node frames, shape (m, 3, 3).
    rest_lengths : Rest lengths l₀ [m], shape (m,).

    Returns
    -------
    Dictionary with ``deformations`` d [m, rad] (m, 7); ``jacobian`` B = ∂d/∂p (m, 7, 12); ``element_frames``
    R_e (m, 3, 3); ``chord_lengths`` l [m] (m,); ``spin_jacobian`` W = ∂(w₁, w₂, w₃)/∂p (m, 3, 12), the
    element frame's spin in its own axes.
    """
    element_frames, lengths, mean_axes = corotational_frames_reference(
        positions_a, positions_b, frames_a, frames_b
    )
    m = lengths.size
    e1, e2, e3 = element_frames[:, :, 0], element_frames[:, :, 1], element_frames[:, :, 2]
    rel_a = np.einsum("mji,mjk->mik", element_frames, frames_a)
    rel_b = np.einsum("mji,mjk->mik", element_frames, frames_b)
    theta_a = rotation_vector(rel_a)
    theta_b = rotation_vector(rel_b)
    q1 = np.einsum("mi,mi->m", mean_axes, e1)
    q2 = np.einsum("mi,mi->m", mean_axes, e2)

    spin = np.zeros((m, 3, 12))
    spin[:, 1, 0:3] = e3 / lengths[:, None]
    spin[:, 1, 6:9] = -e3 / lengths[:, None]
    spin[:, 2, 0:3] = -e2 / lengths[:, None]
    spin[:, 2, 6:9] = e2 / lengths[:, None]
    spin[:, 0] = (q1 / q2)[:, None] * spin[:, 1]
    spin[:, 0, 3:6] += np.cross(frames_a[:, :, 1], e3) / (2.0 * q2[:, None])
    spin[:, 0, 9:12] += np.cross(frames_b[:, :, 1], e3) / (2.0 * q2[:, None])

    jacobian = np.zeros((m, 7, 12))
    jacobian[:, 0, 0:3] = -e1
    jacobian[:, 0, 6:9] = e1
    local_a = -spin.copy()
    local_a[:, :, 3:6] += np.swapaxes(element_frames, 1, 2)
    local_b = -spin.copy()
    local_b[:, :, 9:12] += np.swapaxes(element_frames, 1, 2)
    jacobian[:, 1:4] = left_jacobian_inverse(theta_a) @ local_a
    jacobian[:, 4:7] = left_jacobian_inverse(theta_b) @ local_b

    deformations = np.concatenate([(lengths - rest_lengths)[:, None], theta_a, theta_b], axis=1)
    return {
        "deformations": deformations,
        "jacobian": jacobian,
        "element_frames": element_frames,
        "chord_lengths": lengths,
        "spin_jacobian": spin,
    }


def beam_element_forces(
    positions_a: np.ndarray,
    positions_b: np.ndarray,
    frames_a: np.ndarray,
    frames_b: np.ndarray,
    rest_lengths: np.ndarray,
    reduced_stiffness: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Consistent co-rotational internal forces f = Bᵀ K₇ d of each element, and its strain energy; compiled
    (:func:`local_deformations`, then one kernel for both products), with the bits of
    :func:`beam_element_forces_reference`.

    Parameters
    ----------
    positions_a, positions_b : End node positions [m], shape (m, 3).
    frames_a, frames_b : End node frames, shape (m, 3, 3).
    rest_lengths : Rest lengths l₀ [m], shape (m,).
    reduced_stiffness : K₇, the block of the local stiffness on d = [ū, θ̄_a, θ̄_b], shape (m, 7, 7).

    Returns
    -------
    forces : Internal forces [N] and moments [N·m] on p = [x_a, θ_a, x_b, θ_b], world frame, shape (m, 12).
    energies : Strain energies ½ dᵀ K₇ d [J], shape (m,).
    """
    local = local_deformations(positions_a, positions_b, frames_a, frames_b, rest_lengths)
    stiffness = np.asarray(reduced_stiffness)
    m = local["deformations"].shape[0]
    if stiffness.shape != (m, 7, 7) or stiffness.dtype != np.float64:
        return _forces_of(local, reduced_stiffness)
    return needle_kernels.element_forces(local, stiffness)


def beam_element_forces_reference(
    positions_a: np.ndarray,
    positions_b: np.ndarray,
    frames_a: np.ndarray,
    frames_b: np.ndarray,
    rest_lengths: np.ndarray,
    reduced_stiffness: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Consistent co-rotational internal forces f = Bᵀ K₇ d of each element, and its strain energy, in NumPy:
    the reference of :func:`beam_element_forces`' compiled kernel.

    Parameters
    ----------
    positions_a, positions_b : End node positions [m], shape (m, 3).
    frames_a, frames_b : End node frames, shape (m, 3, 3).
    rest_lengths : Rest lengths l₀ [m], shape (m,).
    reduced_stiffness : K₇, the block of the local stiffness on d = [ū, θ̄_a, θ̄_b], shape (m, 7, 7).

    Returns
    -------
    forces : Internal forces [N] and moments [N·m] on p = [x_a, θ_a, x_b, θ_b], world frame, shape (m, 12).
    energies : Strain energies ½ dᵀ K₇ d [J], shape (m,).
    """
    local = local_deformations_reference(positions_a, positions_b, frames_a, frames_b, rest_lengths)
    return _forces_of(local, reduced_stiffness)


def _forces_of(local: dict, reduced_stiffness: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """f = Bᵀ K₇ d [N, N·m], shape (m, 12), and ½ dᵀ K₇ d [J], shape (m,), from the element kinematics
    ``local`` (:func:`local_deformations`) in NumPy."""
    d = local["deformations"]
    local_forces = np.einsum("mij,mj->mi", reduced_stiffness, d)
    forces = np.einsum("mij,mi->mj", local["jacobian"], local_forces)
    return forces, 0.5 * np.einsum("mi,mi->m", d, local_forces)


def hermite_shapes(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cubic Hermite shapes of a deflection with zero end values and unit end slopes, and their derivatives.

    v(ξ) = l (H_a(ξ) θ_a + H_b(ξ) θ_b) with H_a = ξ (1 − ξ)², H_b = −ξ² (1 − ξ), ξ ∈ [0, 1].

    Parameters
    ----------
    xi : Local coordinates ξ [-], shape (q,).

    Returns
    -------
    shapes : (H_a, H_b), shape (q, 2).
    derivatives : (dH_a/dξ, dH_b/dξ), shape (q, 2).
    """
    xi = np.asarray(xi, dtype=float)
    shapes = np.stack([xi * (1.0 - xi) ** 2, -(xi**2) * (1.0 - xi)], axis=-1)
    derivatives = np.stack([(1.0 - xi) * (1.0 - 3.0 * xi), xi * (3.0 * xi - 2.0)], axis=-1)
    return shapes, derivatives
