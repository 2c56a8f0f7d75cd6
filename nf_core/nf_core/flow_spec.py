"""The one definition of the RealNVP flow's architecture and flat parameter layout.

Both implementations (the torch flow in ``learner_node.flow`` for learning and the compiled
evaluator in ``nf_controller_node.flow_eval`` for the 1 kHz loop) read their weights from a
flat float64 vector in the order defined here, so a parameters message means the same thing
to both.

Flow definition (``n_flow`` elements, each two affine coupling layers with swapped partitions)::

    layer l: c = x[cond_l], z = x[trans_l]
             s = tanh(mlp_s(c)),  t = mlp_t(c)
             y[cond_l] = c,       y[trans_l] = z * exp(s) + t

Each MLP has two hidden layers of ``n_hidden`` units with the chosen activation and a linear
output. The scale is squashed by ``tanh`` so every layer's Jacobian has a bounded, non-zero
diagonal: phi stays a diffeomorphism for every value of the weights.
"""

from __future__ import annotations

from dataclasses import dataclass

ACTIVATIONS = ("gelu", "tanh", "softplus")
ACTIVATION_CODES = {name: i for i, name in enumerate(ACTIVATIONS)}
FLOW_INITS = ("random", "identity")  # initial weights: all random, or s/t output layers zero (phi = x)


@dataclass(frozen=True)
class FlowArchitecture:
    """Shape of the flow: state dimension, number of flow elements, hidden units, activation."""

    dim: int = 3
    n_flow: int = 2
    n_hidden: int = 16
    activation: str = "gelu"

    def __post_init__(self) -> None:
        if self.dim not in (2, 3):
            raise ValueError(f"flow dim must be 2 or 3, got {self.dim}")
        if not 1 <= self.n_flow <= 64:
            raise ValueError(f"n_flow must be in [1, 64], got {self.n_flow}")
        if not 1 <= self.n_hidden <= 1024:
            raise ValueError(f"n_hidden must be in [1, 1024], got {self.n_hidden}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {ACTIVATIONS}, got {self.activation!r}")

    @property
    def n_layers(self) -> int:
        """Number of coupling layers (two per flow element)."""
        return 2 * self.n_flow

    def partition(self, layer: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """(conditioning indices, transformed indices) of coupling layer ``layer``."""
        half = self.dim // 2
        first = tuple(range(half))
        second = tuple(range(half, self.dim))
        return (first, second) if layer % 2 == 0 else (second, first)

    def mlp_shapes(self, d_in: int, d_out: int) -> list[tuple[int, ...]]:
        """Shapes of (W1, b1, W2, b2, W3, b3) of one MLP; W is (out, in), row-major."""
        h = self.n_hidden
        return [(h, d_in), (h,), (h, h), (h,), (d_out, h), (d_out,)]

    def layer_shapes(self, layer: int) -> list[tuple[int, ...]]:
        """Shapes of one coupling layer's parameters: the s-MLP's six arrays, then the t-MLP's."""
        cond, trans = self.partition(layer)
        one = self.mlp_shapes(len(cond), len(trans))
        return one + one

    def param_shapes(self) -> list[tuple[int, ...]]:
        """Shapes of all parameter arrays in flat-vector order."""
        shapes: list[tuple[int, ...]] = []
        for layer in range(self.n_layers):
            shapes.extend(self.layer_shapes(layer))
        return shapes

    @property
    def n_params(self) -> int:
        """Length of the flat weight vector."""
        total = 0
        for shape in self.param_shapes():
            size = 1
            for n in shape:
                size *= n
            total += size
        return total
