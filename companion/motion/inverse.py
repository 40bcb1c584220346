"""Inverse CPG model (thesis sec. 4.5.1) and parameter adaptation (eq. 4.3), numpy and scipy only.

``xi = [v; omega; theta]`` (R^7, :mod:`.steady`) is first encoded by an autoencoder with a 4-d
hidden layer ``h``, which projects a desired motion onto the motions the CPG can make; a tanh
MLP maps ``h`` to the CPG parameters ``eta = [A; B]``. The same model serves the thesis's snake
(sec. 4.5.2: ``xi = [v_x; v_y; omega]``, ``h`` and ``eta = [A; B]`` in R^2; ``bottleneck`` of
:func:`train_inverse_model`). Both are small fully connected networks
(tanh hidden layers, linear outputs; the bottleneck is tanh) on standardised data, trained by
L-BFGS (scipy) on mean squared error with a little weight decay, from seeded initial weights.

Eq. 4.3 adapts the parameters in the hidden space:
``Delta eta = -(d eta / d h) (k_p (h - h_d) + k_i int (h - h_d) dt)``, with ``d eta / d h`` the
MLP's analytic Jacobian (:meth:`InverseModel.eta_jacobian`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from companion.configfile import ConfigError, build, to_dict

from .steady import SteadyConfig

__all__ = ["Mlp", "train_mlp", "InverseModel", "train_inverse_model", "nearest_feasible", "Adaptation", "SteadyGate",
           "MODEL_VERSION"]

#: 2: the file records the expected physics and CPG the data came from (``steady``)
MODEL_VERSION = 2


@dataclass(frozen=True)
class Mlp:
    """Layers ``(W, b)``; tanh on every hidden layer and, if ``tanh_out``, on the output."""

    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]
    tanh_out: bool = False

    @classmethod
    def init(cls, sizes: tuple[int, ...], rng: np.random.Generator, tanh_out: bool = False) -> Mlp:
        ws = tuple(rng.normal(scale=1.0 / np.sqrt(m), size=(m, k)) for m, k in zip(sizes[:-1], sizes[1:]))
        return cls(ws, tuple(np.zeros(k) for k in sizes[1:]), tanh_out)

    def forward(self, x: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        """Output and the activations of every layer (input first)."""
        acts = [x]
        for k, (W, b) in enumerate(zip(self.weights, self.biases)):
            z = acts[-1] @ W + b
            last = k == len(self.weights) - 1
            acts.append(np.tanh(z) if (not last or self.tanh_out) else z)
        return acts[-1], acts

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self.forward(x)[0]

    def backward(self, acts: list[np.ndarray], grad_out: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
        """Gradients of a loss with ``dL/dy = grad_out``: ``(dW per layer, db per layer, dL/dx)``."""
        dWs, dbs = [], []
        g = grad_out
        for k in range(len(self.weights) - 1, -1, -1):
            last = k == len(self.weights) - 1
            if not last or self.tanh_out:
                g = g * (1.0 - acts[k + 1] ** 2)
            dWs.append(acts[k].T @ g)
            dbs.append(g.sum(axis=0))
            g = g @ self.weights[k].T
        return dWs[::-1], dbs[::-1], g

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """(out, in) Jacobian of the network at one input ``x``."""
        _, acts = self.forward(x[None])
        J = np.eye(self.weights[-1].shape[1])
        for k in range(len(self.weights) - 1, -1, -1):
            last = k == len(self.weights) - 1
            if not last or self.tanh_out:
                J = J * (1.0 - acts[k + 1][0] ** 2)[None, :]
            J = J @ self.weights[k].T
        return J

    def flat(self) -> np.ndarray:
        return np.concatenate([a.ravel() for pair in zip(self.weights, self.biases) for a in pair])

    def with_flat(self, theta: np.ndarray) -> Mlp:
        ws, bs, i = [], [], 0
        for W, b in zip(self.weights, self.biases):
            ws.append(theta[i:i + W.size].reshape(W.shape))
            i += W.size
            bs.append(theta[i:i + b.size].copy())
            i += b.size
        return Mlp(tuple(ws), tuple(bs), self.tanh_out)


def _fit(nets: list[Mlp], loss_and_grads, decay: float, max_iter: int) -> list[Mlp]:
    """L-BFGS over the weights of ``nets`` jointly; ``loss_and_grads(nets) -> (loss, grads per net)``."""
    # (imported here, where a model is trained: every process that reads a setup imports this
    # module, and scipy.optimize would cost each of them 0.16 s and 22 MB)
    from scipy.optimize import minimize

    sizes = [n.flat().size for n in nets]

    def split(theta):
        out, i = [], 0
        for n, s in zip(nets, sizes):
            out.append(n.with_flat(theta[i:i + s]))
            i += s
        return out

    def fun(theta):
        cur = split(theta)
        loss, grads = loss_and_grads(cur)
        return loss + decay * theta @ theta, np.concatenate(grads) + 2 * decay * theta

    res = minimize(fun, np.concatenate([n.flat() for n in nets]), jac=True, method="L-BFGS-B",
                   options={"maxiter": max_iter})
    return split(res.x)


def _grads_flat(net: Mlp, dWs, dbs) -> np.ndarray:
    return np.concatenate([a.ravel() for pair in zip(dWs, dbs) for a in pair])


def train_mlp(x: np.ndarray, y: np.ndarray, hidden: int, rng: np.random.Generator, decay: float = 1e-5,
              max_iter: int = 2000) -> Mlp:
    """Least-squares fit of a one-hidden-layer tanh MLP ``x -> y``."""
    net = Mlp.init((x.shape[1], hidden, y.shape[1]), rng)

    def loss(nets):
        out, acts = nets[0].forward(x)
        err = out - y
        dWs, dbs, _ = nets[0].backward(acts, 2 * err / len(x))
        return float(np.mean(np.sum(err ** 2, axis=1))), [_grads_flat(nets[0], dWs, dbs)]

    return _fit([net], loss, decay, max_iter)[0]


@dataclass(frozen=True)
class InverseModel:
    """Encoder ``xi -> h`` (and decoder ``h -> xi``) and the MLP ``h -> eta``, with the
    standardisation of ``xi`` and ``eta`` they were trained on, and ``steady``: the chain, CPG
    and expected physics that made the data (a generator must run the same to be inverted;
    ``None`` for a robot simulated elsewhere, whose ``info`` says how)."""

    encoder: Mlp
    decoder: Mlp
    to_eta: Mlp
    xi_mean: np.ndarray
    xi_std: np.ndarray
    eta_mean: np.ndarray
    eta_std: np.ndarray
    steady: SteadyConfig | None = field(default_factory=SteadyConfig)
    #: the range of the training parameters: outside it the model extrapolates
    eta_low: np.ndarray = field(default_factory=lambda: np.full(4, -np.inf))
    eta_high: np.ndarray = field(default_factory=lambda: np.full(4, np.inf))
    info: dict = field(default_factory=dict)

    def encode(self, xi: np.ndarray) -> np.ndarray:
        return self.encoder((np.atleast_2d(xi) - self.xi_mean) / self.xi_std)

    def decode(self, h: np.ndarray) -> np.ndarray:
        """``AE(xi)`` after :meth:`encode`: the nearest motion the CPG can make."""
        return self.decoder(np.atleast_2d(h)) * self.xi_std + self.xi_mean

    def eta_of_h(self, h: np.ndarray) -> np.ndarray:
        return self.to_eta(np.atleast_2d(h)) * self.eta_std + self.eta_mean

    def __call__(self, xi: np.ndarray) -> np.ndarray:
        """``Xi^-1(xi)``: CPG parameters for desired motions (K, 7) -> (K, 4)."""
        return self.eta_of_h(self.encode(xi))

    def eta_jacobian(self, h: np.ndarray) -> np.ndarray:
        """(len(eta), len(h)) ``d eta / d h`` at one hidden vector (eq. 4.3), analytic."""
        return self.eta_std[:, None] * self.to_eta.jacobian(np.asarray(h, dtype=float))

    def save(self, path: str | Path) -> None:
        arrays = {"version": np.array(MODEL_VERSION)}
        for name in ("encoder", "decoder", "to_eta"):
            net = getattr(self, name)
            for k, (W, b) in enumerate(zip(net.weights, net.biases)):
                arrays[f"{name}_W{k}"], arrays[f"{name}_b{k}"] = W, b
            arrays[f"{name}_tanh_out"] = np.array(net.tanh_out)
        for name in ("xi_mean", "xi_std", "eta_mean", "eta_std", "eta_low", "eta_high"):
            arrays[name] = getattr(self, name)
        arrays["steady"] = np.array(json.dumps(None if self.steady is None else to_dict(self.steady)))
        arrays["info"] = np.array(json.dumps(self.info))
        np.savez_compressed(path, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> InverseModel:
        data = np.load(path)
        version = int(data["version"])
        if version != MODEL_VERSION:
            raise ValueError(f"{path}: inverse model format version {version}, this code reads {MODEL_VERSION} "
                             "(regenerate it: companion/motion/models/README.md)")
        try:
            record = json.loads(str(data["steady"]))
            steady = None if record is None else build(SteadyConfig, record, file=str(path), prefix="steady")
        except (KeyError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: no readable physics record ({exc})") from None
        except ConfigError as exc:
            raise ValueError(str(exc)) from None

        def net(name: str) -> Mlp:
            k = 0
            ws, bs = [], []
            while f"{name}_W{k}" in data:
                ws.append(data[f"{name}_W{k}"])
                bs.append(data[f"{name}_b{k}"])
                k += 1
            return Mlp(tuple(ws), tuple(bs), bool(data[f"{name}_tanh_out"]))

        return cls(net("encoder"), net("decoder"), net("to_eta"), data["xi_mean"], data["xi_std"],
                   data["eta_mean"], data["eta_std"], steady, data["eta_low"], data["eta_high"],
                   {**json.loads(str(data["info"])), "file": str(path)})


def train_inverse_model(eta: np.ndarray, xi: np.ndarray, seed: int = 0, hidden: int = 24, decay: float = 1e-5,
                        max_iter: int = 3000, steady: SteadyConfig | None = SteadyConfig(), bottleneck: int = 4,
                        info: dict | None = None) -> InverseModel:
    """Train the autoencoder on ``xi`` (a tanh bottleneck of ``bottleneck``), then the MLP from its
    hidden layer to ``eta`` (thesis sec. 4.5.1); ``steady``: how the data was simulated (recorded),
    ``info``: more to record with the model."""
    rng = np.random.default_rng(seed)
    xi_mean, xi_std = xi.mean(axis=0), xi.std(axis=0) + 1e-9
    eta_mean, eta_std = eta.mean(axis=0), eta.std(axis=0) + 1e-9
    x = (xi - xi_mean) / xi_std
    y = (eta - eta_mean) / eta_std
    enc = Mlp.init((x.shape[1], hidden, bottleneck), rng, tanh_out=True)
    dec = Mlp.init((bottleneck, hidden, x.shape[1]), rng)

    def ae_loss(nets):
        e, d = nets
        h, acts_e = e.forward(x)
        out, acts_d = d.forward(h)
        err = out - x
        dWd, dbd, gh = d.backward(acts_d, 2 * err / len(x))
        dWe, dbe, _ = e.backward(acts_e, gh)
        return float(np.mean(np.sum(err ** 2, axis=1))), [_grads_flat(e, dWe, dbe), _grads_flat(d, dWd, dbd)]

    enc, dec = _fit([enc, dec], ae_loss, decay, max_iter)
    h = enc(x)
    to_eta = train_mlp(h, y, hidden, rng, decay, max_iter)
    recon = float(np.sqrt(np.mean((dec(h) - x) ** 2)))
    fit = float(np.sqrt(np.mean((to_eta(h) - y) ** 2)))
    return InverseModel(enc, dec, to_eta, xi_mean, xi_std, eta_mean, eta_std, steady, eta.min(axis=0), eta.max(axis=0),
                        {**(info or {}), "seed": seed, "hidden": hidden, "bottleneck": bottleneck, "samples": len(xi),
                         "ae_rmse_std": recon, "eta_rmse_std": fit})


def nearest_feasible(model: InverseModel, points, s: np.ndarray) -> float:
    """The parameter of the curve ``points(s)`` ((K,) -> (K, len(xi))) nearest the motions the
    CPG can make: the ``s`` of the grid whose point the autoencoder reconstructs best (standardised
    distance to ``AE(x)``), refined by a parabola through it and its neighbours (thesis sec. 4.5.3,
    Fig. 4-11: where the curve of the desired motions crosses the feasible set)."""
    s = np.asarray(s, dtype=float)
    x = points(s)
    r = (model.decode(model.encode(x)) - x) / model.xi_std
    e = np.sum(r * r, axis=1)
    k = int(np.clip(np.argmin(e), 1, s.size - 2))
    den = e[k - 1] - 2.0 * e[k] + e[k + 1]
    best = s[k] + (0.5 * (e[k - 1] - e[k + 1]) / den * (s[1] - s[0]) if den > 0 else 0.0)
    return float(np.clip(best, s[k - 1], s[k + 1]))


@dataclass
class Adaptation:
    """Eq. 4.3: PI adaptation of the CPG parameters in the hidden space, ``k_p``, ``k_i`` gains."""

    model: InverseModel
    k_p: float = 0.5
    k_i: float = 0.2
    integral: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.integral is None:
            self.integral = np.zeros(self.model.encoder.weights[-1].shape[1])

    def update(self, xi_desired: np.ndarray, xi_measured: np.ndarray, dt_s: float) -> np.ndarray:
        """The adapted parameters ``eta = eta_raw + Delta eta`` for this step, limited to the
        model's training range; the integral stops growing while the result is limited (anti
        wind-up: a motion the CPG cannot make must not drive the parameters ever further)."""
        m = self.model
        h_d = m.encode(xi_desired)[0]
        h = m.encode(xi_measured)[0]
        raw = m.eta_of_h(h_d)[0]
        J = m.eta_jacobian(h_d)
        integral = self.integral + (h - h_d) * dt_s
        eta = raw - J @ (self.k_p * (h - h_d) + self.k_i * integral)
        limited = np.clip(eta, m.eta_low, m.eta_high)
        if np.array_equal(limited, eta):
            self.integral = integral
        else:
            limited = np.clip(raw - J @ (self.k_p * (h - h_d) + self.k_i * self.integral), m.eta_low, m.eta_high)
        return limited


@dataclass
class SteadyGate:
    """When the adaptation may run: on steady motion only (what the inverse model maps), at least
    ``settle_periods`` periods after a new command and once the period-averaged velocity changes by
    less than ``steady_tol`` (relative) from one period to the next. Adapting on the acceleration
    transient would wind the integral up."""

    settle_periods: int = 2
    steady_tol: float = 0.02
    _periods: int = 0
    _previous: np.ndarray | None = None

    def restart(self) -> None:
        """A new command: the settling starts again."""
        self._periods = 0

    def steady(self, velocity: np.ndarray) -> bool:
        """Whether the period that ended with the mean ``velocity`` is steady (counts the period)."""
        velocity = np.asarray(velocity, dtype=float)
        change = (np.inf if self._previous is None else np.linalg.norm(velocity - self._previous)
                  / max(float(np.linalg.norm(velocity)), 1e-3))
        self._previous = velocity
        self._periods += 1
        return self._periods > self.settle_periods and change < self.steady_tol
