r"""How a matrix group and its Lie algebra are held in arrays, and computed with: the
representation a system may declare through its velocity map.

The reduced step (`clebsch_jax.discrete.reduction`) is written with a handful of operations
on the group's matrices: the algebra element $X(\xi)$ of the velocity's coordinates, its
adjoint $X^T$ under the pairings, the adjoint $A^\dagger$ of a matrix, products and solves,
and the passage between the configuration Q as the engine stores it and the group's matrix.
`RealMatrices` is the default form of those operations — real matrices, $A^\dagger = A^T$,
the Frobenius pairing, Q its own matrix — which every reduction the engine finds by itself
uses. A model whose group is better computed in another form declares it: its velocity map
is a `MatrixRepresentation`, right multiplication in that representation, and the engine
takes its operations from it instead of inspecting the map (Theorem 12's closure is the
representation's own statement: $X$ maps onto a Lie algebra).

`UnitaryAlgebra(n)` is one: $U(n)$ with complex n×n products, where the real form
$\mathfrak{gl}(2n, \mathbb R)$ of the same group carries four times the numbers and twice the
flops per product.

**Pairings and gradients.** The engine's unknowns stay real arrays (ξ's coordinates, the body
momentum μ), paired by the Frobenius product, and its gradients are `jax.grad` of real
functions of them; complex arrays live only inside the reduced step's products, paired by
$\langle A, B\rangle = \mathrm{Re\,tr}(A^\dagger B)$. `X_adjoint` is the adjoint of `X` for
these two pairings: $\langle X(\eta), M\rangle = \eta\cdot X^T(M)$. (JAX's `jax.grad` of a
real function $f$ of a complex array $z = x + iy$ returns $\partial f/\partial x -
i\,\partial f/\partial y$, the conjugate of the Riesz gradient of this pairing: code that
differentiates with respect to a complex matrix conjugates it. The reduced step does not:
it differentiates only with respect to the real coordinates.)
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from . import linalg as _linalg

__all__ = ["RealMatrices", "MatrixRepresentation", "UnitaryAlgebra"]


class RealMatrices:
    r"""The default form of the reduced step's operations: the group's matrices are real
    arrays, the configuration is its own matrix, $A^\dagger = A^T$ (the Frobenius pairing's
    adjoint). A reduction supplies `X`, `X_inv`, `X_adjoint`, `X_inv_adjoint` and
    `xi_shape`; these are the rest."""

    ambient_complex = False
    skew_adjoint = False
    r"""True when every $X(\xi)$ is anti-self-adjoint, $X(\xi)^\dagger = -X(\xi)$ (so(n),
    u(n)): the Cayley step's sandwich is then a congruence, and both its momentum maps follow
    from one product $C = YP$ (`cayley_parts`)."""

    def X_adjoint_congruence(self, L, P):
        r"""$X^T(L P L^\dagger)$: the adjoint of a congruence. The reduced Cayley step's
        residual is $X^T(F_-^\dagger P F_+^\dagger)$, a congruence with $L = F_-^\dagger$ when the
        algebra is `skew_adjoint`. Here as written; a representation may use that the result
        lies in its algebra."""
        return self.X_adjoint(self.matmul(self.matmul(L, P), self.dagger(L)))

    def cayley_parts(self, Y, P):
        r"""The reduced Cayley step's momentum maps for a `skew_adjoint` algebra, as the parts of
        $X^T(F_-^\dagger P F_+^\dagger)$ even and odd in Δt ($Y = \Delta t X(\xi)$, $F_\mp = I
        \mp Y/2$, so $F_-^\dagger = I + Y/2$ and $F_+^\dagger = I - Y/2$): with $C = YP$, and
        $PY = C^\dagger$ when P is in the algebra too,

        $$ (I + Y/2)P(I - Y/2) = P + \tfrac12(C - C^\dagger) - \tfrac14 CY , \qquad
           \text{even} = X^T(P) - \tfrac14 X^T(CY), \quad \text{odd} = X^T(C) , $$

        ($X^T(C^\dagger) = -X^T(C)$ for the pairings' adjoint of an anti-self-adjoint X). The
        residual is $\mu - \text{even} - \text{odd}$ and the outgoing momentum's increment
        $X^T(Y^\dagger P - PY^\dagger) = -2\,\text{odd}$ (`reduction._cayley_step`): the
        step's O(Δt) terms are formed as products of the small Y, not recovered from products
        of O(1) matrices. Here as written; a representation may compute $X^T(CY)$ knowing that
        CY lies in its algebra. **Returns:** `(even, odd)`."""
        C = self.matmul(Y, P)
        return self.X_adjoint(P) - 0.25 * self.X_adjoint(self.matmul(C, Y)), self.X_adjoint(C)

    @staticmethod
    def dagger(A):
        return jnp.swapaxes(A, -1, -2)

    @staticmethod
    def matmul(A, B):
        return _linalg.matmul(A, B)

    @staticmethod
    def solve(A, B):
        return _linalg.solve(A, B, unroll=True)

    @staticmethod
    def to_ambient(Q):
        return Q

    @staticmethod
    def from_ambient(M):
        return M


class MatrixRepresentation(RealMatrices):
    r"""A velocity map $\mathcal L_\xi Q = Q\,X(\xi)$ that states how its group is computed
    (subclass and give `X`, `X_adjoint`, `X_inv`, `X_inv_adjoint`, `xi_shape` and, for
    another form than the real one, `dagger`, `matmul`, `solve`, `to_ambient`,
    `from_ambient`). Called as the velocity map, `rep(xi, Q)` is
    `from_ambient(to_ambient(Q) @ X(xi))` (the engine's full march and its model checks use
    that); the reduced step uses the operations themselves. Instances must be hashable (they
    are static in compiled programs)."""

    def __call__(self, xi, Q):
        return self.from_ambient(self.matmul(self.to_ambient(Q), self.X(xi)))


@dataclasses.dataclass(frozen=True)
class UnitaryAlgebra(MatrixRepresentation):
    r"""$U(n)$ and $\mathfrak u(n)$ in complex arithmetic, with ξ a *real* n×n matrix S of
    coordinates: $X(S) = \tfrac12(S - S^T) + \tfrac i2(S + S^T)$, a bijection of
    $\mathbb R^{n\times n}$ onto the skew-Hermitian matrices (real part antisymmetric,
    imaginary part symmetric) and an isometry, $\langle S_1, S_2\rangle =
    \mathrm{Re\,tr}(X(S_1)^\dagger X(S_2))$: dim V = n², the dimension of $\mathfrak u(n)$,
    and $X^{-1} = X^T$ on it.

    The configuration Q is stored in the real form $R(A + iB) = \begin{pmatrix} A & -B \\ B & A
    \end{pmatrix}$ (2n×2n), a real matrix group in which the velocity map
    $Q \mapsto Q\,R(X(S))$ is right multiplication (the full march runs on it as on any matrix
    group); the reduced step computes with n×n complex matrices, $A^\dagger$ the conjugate
    transpose. Use it as the velocity map: `ClebschSystem(velocity_map=UnitaryAlgebra(n), ...)`
    (`clebsch_jax.models.euler_sphere`)."""

    n: int

    ambient_complex = True
    skew_adjoint = True

    def __post_init__(self):
        if isinstance(self.n, bool) or not isinstance(self.n, int) or self.n < 1:
            raise ValueError(f"n: expected a positive integer matrix size, got {self.n!r}.")

    @property
    def xi_shape(self):
        return (self.n, self.n)

    def X(self, xi):
        xt = jnp.swapaxes(xi, -1, -2)
        return jax.lax.complex(0.5 * (xi - xt), 0.5 * (xi + xt))

    def X_adjoint(self, M):
        re, im = jnp.real(M), jnp.imag(M)
        return 0.5 * (re - jnp.swapaxes(re, -1, -2)) + 0.5 * (im + jnp.swapaxes(im, -1, -2))

    def X_inv(self, M):
        return self.X_adjoint(M)

    def X_inv_adjoint(self, g):
        return self.X(g)

    @staticmethod
    def dagger(A):
        return jnp.conj(jnp.swapaxes(A, -1, -2))

    @staticmethod
    def matmul(A, B):
        r"""$(a + ib)(c + id)$ by three real products (Gauss's; the "3M" method):
        $ac - bd + i\,((a + b)(c + d) - ac - bd)$. XLA's CPU backend runs a complex product
        as slowly as four real ones; three cost less (`benchmarks/README.md`, issue 43). The
        imaginary part's rounding is bounded by $\varepsilon(|a| + |b|)(|c| + |d|)$ instead of
        $\varepsilon(|a||d| + |b||c|)$: the same order."""
        a, b, c, d = jnp.real(A), jnp.imag(A), jnp.real(B), jnp.imag(B)
        ac, bd = _linalg.matmul(a, c), _linalg.matmul(b, d)
        return jax.lax.complex(ac - bd, _linalg.matmul(a + b, c + d) - ac - bd)

    def cayley_parts(self, Y, P):
        r"""`RealMatrices.cayley_parts` in five real n×n products, none of a transposed operand
        (XLA's CPU backend runs a product $A^TB$ by a slower route than $AB$): $C = YP$ by
        `matmul` (three), and $X^T(CY) = \mathrm{Re}(CY) + \mathrm{Im}(CY)$ (CY is
        skew-Hermitian, up to rounding) $= c_r(y_r + y_i) + c_i(y_r - y_i)$ (two)."""
        C = self.matmul(Y, P)
        cr, ci, yr, yi = jnp.real(C), jnp.imag(C), jnp.real(Y), jnp.imag(Y)
        CY = _linalg.matmul(cr, yr + yi) + _linalg.matmul(ci, yr - yi)
        return self.X_adjoint(P) - 0.25 * CY, self.X_adjoint(C)

    @staticmethod
    def solve(A, B):
        return _linalg.solve(A, B)

    def to_ambient(self, Q):
        n = self.n
        return jax.lax.complex(0.5 * (Q[..., :n, :n] + Q[..., n:, n:]), 0.5 * (Q[..., n:, :n] - Q[..., :n, n:]))

    @staticmethod
    def from_ambient(M):
        A, B = jnp.real(M), jnp.imag(M)
        return jnp.concatenate([jnp.concatenate([A, -B], axis=-1), jnp.concatenate([B, A], axis=-1)], axis=-2)

    def __call__(self, xi, Q):
        # right multiplication by R(X(ξ)) on every real 2n×2n matrix, not only those of the
        # form R(Z) (`to_ambient` keeps only that part), so that the map is what it says
        return _linalg.matmul(Q, self.from_ambient(self.X(xi)))
