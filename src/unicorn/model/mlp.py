"""Fully connected heads, laid out like the reference's ``create_mlp`` so released weights map one to one."""

from __future__ import annotations

from torch import nn

__all__ = ["MLP"]


class MLP(nn.Sequential):
    """``Linear -> ReLU`` repeated ``n_layers`` times, then a last ``Linear`` (no output activation).

    Linear layers sit at the even indices ``0, 2, 4, ...`` of the sequence, which gives the state-dict names
    ``0.weight``, ``2.weight``, ... of the reference. Hidden layers are Kaiming-normal initialised (ReLU gain)
    with zero biases; ``zero_last=True`` zeroes the last layer so that the head outputs exactly 0 at init.

    Args:
        in_features: input size.
        out_features: output size.
        n_units: hidden width (128 in UNICORN).
        n_layers: number of hidden layers (3 in UNICORN; 0 gives a single linear layer).
        zero_last: zero the last layer's weight and bias.

    Shapes:
        (..., in_features) -> (..., out_features).
    """

    def __init__(
        self,
        in_features: int,
        out_features: int,
        n_units: int = 128,
        n_layers: int = 3,
        zero_last: bool = False,
    ) -> None:
        if min(in_features, out_features, n_units) < 1 or n_layers < 0:
            raise ValueError(
                f"invalid MLP sizes: in={in_features}, out={out_features}, units={n_units}, layers={n_layers}"
            )
        layers: list[nn.Module] = []
        width = in_features
        for _ in range(n_layers):
            layers += [nn.Linear(width, n_units), nn.ReLU(inplace=True)]
            width = n_units
        layers.append(nn.Linear(width, out_features))
        super().__init__(*layers)
        self.in_features = in_features
        self.out_features = out_features
        for layer in self:
            if isinstance(layer, nn.Linear):
                nn.init.kaiming_normal_(layer.weight, nonlinearity="relu")
                nn.init.zeros_(layer.bias)
        if zero_last:
            nn.init.zeros_(self[-1].weight)
            nn.init.zeros_(self[-1].bias)
