"""A conditional normalising flow as an amortised posterior estimator (flowjax on JAX, CPU).

Neural posterior estimation (Papamakarios & Murray 2016; Greenberg et al. 2019): a flow
q(theta | x) is fitted by maximum likelihood to pairs (theta, x) drawn from the prior and the
simulator, and then gives the posterior of any tree's summaries x in one pass.

* **Parameters.** Each lives in its prior's bounds; the flow works on the logit of its place in
  them (so every draw lies inside), standardised. A whole-number parameter is widened by half a
  step at each end and its training values are spread uniformly over their step (dequantisation),
  so that the flow sees a density, not spikes; its draws are rounded back.
* **Summaries.** Standardised by their training mean and sd; a tree's summaries are clipped to
  10 sd, so that one far outside the training set cannot send the flow into its tails.
* **Flow.** ``layers`` coupling layers of rational-quadratic splines (Durkan et al. 2019,
  "Neural spline flows") with ``knots`` knots on [-5, 5], conditioners of ``depth`` hidden
  layers of ``width`` units taking the summaries; Adam with gradient clipping, mini-batches of
  ``batch``, a validation share ``validation`` and early stopping after ``patience`` epochs
  without a better validation loss (the best weights are kept).
* **Ensemble.** ``ensemble`` flows trained from other seeds; the posterior draws equally from
  each. A mixture of flows is wider where they disagree, which guards against the over-confident
  intervals a single flow can give (Hermans et al. 2022, "A trust crisis in simulation-based
  inference?").

Everything random is seeded: the same data, settings and seed give the same weights, and the
same weights, summaries and seed the same draws (on one machine and library version).
"""

from __future__ import annotations

import importlib.util
import io
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np
from pydantic import Field

from bforest_core.interfaces import AmortisedEstimator, ComponentSettings

#: what the extra installs, in the order they are checked
LIBRARIES = ("jax", "jaxlib", "flowjax", "equinox", "optax")
INSTALL = "pip install 'bayesforest[amortised]'"
#: summaries are clipped to this many training sd
CLIP_SD = 10.0
#: the splines' interval: identity outside [-B, B] of the standardised parameters
SPLINE_BOUND = 5.0
_EPS = 1e-6


class FlowSettings(ComponentSettings):
    """Settings of the ``flow`` estimator."""

    layers: int = Field(5, ge=1, le=32, description="coupling layers of the flow")
    knots: int = Field(8, ge=2, le=64, description="knots of each rational-quadratic spline")
    width: int = Field(64, ge=4, le=1024, description="units of each hidden layer of a conditioner")
    depth: int = Field(2, ge=1, le=8, description="hidden layers of a conditioner")
    learning_rate: float = Field(5e-4, gt=0, le=0.1, description="Adam's step size")
    batch: int = Field(256, ge=8, description="training pairs per step")
    max_epochs: int = Field(400, ge=1, description="most passes over the training pairs")
    patience: int = Field(20, ge=1, description="epochs without a better validation loss before training stops")
    validation: float = Field(0.1, gt=0, lt=0.5, description="share of the pairs kept for validation")
    ensemble: int = Field(
        1, ge=1, le=16, description="flows trained from different seeds; the posterior draws equally from each"
    )


def missing_libraries() -> str | None:
    """One line naming the first missing library and what to install, or None."""
    for name in LIBRARIES:
        if importlib.util.find_spec(name) is None:
            return f"the amortised estimator needs JAX and flowjax ({name} is not installed): {INSTALL}"
    return None


#: where JAX keeps the code it compiles for the flows ("off": nowhere)
CACHE_ENV = "BFOREST_JAX_CACHE"


def _jax():
    """Import JAX on the CPU (no accelerator is probed), with a persistent compilation cache.

    Compiling a flow's sampling takes seconds on a first call; the cache (``$BFOREST_JAX_CACHE``,
    default the user's cache folder's ``bayesforest/jax``; ``off`` for none) keeps the compiled
    code for the next process, so a posterior after the first takes a second or two.
    """
    import os

    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    import jax

    global _CACHE_SET
    if not _CACHE_SET:
        _CACHE_SET = True
        where = os.environ.get(CACHE_ENV, "")
        if where.lower() != "off":
            from bforest_core.samples import cache_dir

            jax.config.update(
                "jax_compilation_cache_dir", str(Path(where).expanduser() if where else cache_dir() / "jax")
            )
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
            jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    return jax


_CACHE_SET = False


class _Transform:
    """Parameters <-> the flow's standardised logits, summaries -> standardised summaries."""

    def __init__(self, lower, upper, integer, zm=None, zs=None, xm=None, xs=None):
        self.lower, self.upper = np.asarray(lower, float), np.asarray(upper, float)
        self.integer = np.asarray(integer, bool)
        self.lo = np.where(self.integer, self.lower - 0.5, self.lower)
        self.hi = np.where(self.integer, self.upper + 0.5, self.upper)
        self.zm, self.zs, self.xm, self.xs = zm, zs, xm, xs

    def logit(self, theta: np.ndarray) -> np.ndarray:
        u = np.clip((theta - self.lo) / (self.hi - self.lo), _EPS, 1.0 - _EPS)
        return np.log(u) - np.log1p(-u)

    def fit(self, theta: np.ndarray, x: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Fit the standardisations on the training pairs; return them transformed."""
        theta = np.array(theta, float)
        spread = rng.uniform(-0.5, 0.5, size=theta.shape)
        theta[:, self.integer] += spread[:, self.integer]  # dequantise whole numbers over their step
        z = self.logit(theta)
        self.zm, self.zs = z.mean(0), np.maximum(z.std(0), 1e-6)
        self.xm, sd = x.mean(0), x.std(0)
        self.xs = np.where(sd > 1e-12, sd, 1.0)
        return (z - self.zm) / self.zs, self.summaries(x)

    def summaries(self, x: np.ndarray) -> np.ndarray:
        return np.clip((np.asarray(x, float) - self.xm) / self.xs, -CLIP_SD, CLIP_SD)

    def parameters(self, z: np.ndarray) -> np.ndarray:
        u = 1.0 / (1.0 + np.exp(-(np.asarray(z, float) * self.zs + self.zm)))
        theta = self.lo + u * (self.hi - self.lo)
        return np.where(self.integer, np.clip(np.round(theta), self.lower, self.upper), theta)

    def meta(self) -> dict:
        return {k: np.asarray(getattr(self, k)).tolist() for k in ("lower", "upper", "integer", "zm", "zs", "xm", "xs")}

    @classmethod
    def from_meta(cls, meta: dict) -> _Transform:
        arr = {k: np.asarray(meta[k], float) for k in ("zm", "zs", "xm", "xs")}
        return cls(meta["lower"], meta["upper"], np.asarray(meta["integer"], bool), **arr)


class FlowEstimator(AmortisedEstimator):
    """Conditional neural spline flow (flowjax) of the parameters given a tree's summaries."""

    name = "flow"
    summary = (
        "conditional neural spline flow (flowjax on JAX, CPU): posterior of the parameters given a tree's summaries"
    )
    Settings = FlowSettings

    def __init__(self, settings=None, **kwargs):
        super().__init__(settings, **kwargs)
        self._flows = None  # the trained flows (a list, one per ensemble member)
        self._tf: _Transform | None = None
        self._dims: tuple[int, int] | None = None

    # -------------------------------------------------------------------------- capabilities
    def missing(self) -> str | None:
        return missing_libraries()

    def library_versions(self) -> dict[str, str]:
        out = {}
        for name in LIBRARIES:
            try:
                out[name] = version(name)
            except PackageNotFoundError:
                out[name] = "not installed"
        return out

    @classmethod
    def shipped(cls) -> dict[str, Path]:
        folder = Path(__file__).resolve().parent / "estimators"
        return {p.name.split("_")[0]: p for p in sorted(folder.glob("*_pine.npz"))}

    # -------------------------------------------------------------------------- the flows
    def _need(self) -> None:
        problem = self.missing()
        if problem:
            from bforest_core.errors import PluginError

            raise PluginError(problem)

    def _transformer(self):
        from flowjax.bijections import RationalQuadraticSpline

        return RationalQuadraticSpline(knots=self.settings.knots, interval=SPLINE_BOUND)

    def _build(self, key, p: int, m: int):
        """One untrained flow of ``p`` parameters conditioned on ``m`` summaries."""
        import jax.numpy as jnp
        from flowjax.distributions import Normal
        from flowjax.flows import coupling_flow

        s = self.settings
        return coupling_flow(
            key,
            base_dist=Normal(jnp.zeros(p)),
            transformer=self._transformer(),
            cond_dim=m,
            flow_layers=s.layers,
            nn_width=s.width,
            nn_depth=s.depth,
        )

    def _skeleton(self, p: int, m: int, k: int):
        """``k`` flows of the trained ones' structure whose weights are yet to be filled in.

        Built abstractly (``eqx.filter_eval_shape``: no random initialisation, whose first run
        compiles hundreds of small operations, seconds). A coupling layer's transformer
        constructor is a closure over the spline's initial values, which an abstract build leaves
        abstract: it is built again concretely (it depends on the spline's settings only).
        """
        jax = _jax()
        import equinox as eqx
        import paramax
        from flowjax.bijections import Coupling
        from flowjax.utils import get_ravelled_pytree_constructor

        like = eqx.filter_eval_shape(lambda: [self._build(jax.random.key(j), p, m) for j in range(k)])
        constructor, _ = get_ravelled_pytree_constructor(
            self._transformer(),
            filter_spec=eqx.is_inexact_array,
            is_leaf=lambda leaf: isinstance(leaf, paramax.NonTrainable),
        )

        def couplings(tree):
            nodes = jax.tree_util.tree_leaves(tree, is_leaf=lambda x: isinstance(x, Coupling))
            return [c.transformer_constructor for c in nodes if isinstance(c, Coupling)]

        return eqx.tree_at(couplings, like, [constructor] * len(couplings(like)))

    def train(self, theta, x, lower, upper, integer, seed: int) -> dict:
        self._need()
        jax = _jax()
        import optax
        from flowjax.train import fit_to_data

        theta, x = np.asarray(theta, float), np.asarray(x, float)
        if theta.ndim != 2 or x.ndim != 2 or len(theta) != len(x):
            raise ValueError(f"train: theta {theta.shape} and x {x.shape} must be (n, p) and (n, m)")
        s = self.settings
        if len(theta) < 2 * s.batch:
            raise ValueError(
                f"train: {len(theta)} training pairs are too few for batches of {s.batch} (need {2 * s.batch})"
            )
        tf = _Transform(lower, upper, integer)
        z, xs = tf.fit(theta, x, np.random.default_rng([int(seed), 0xF10]))
        n, p = z.shape
        m = xs.shape[1]
        key = jax.random.key(int(seed))
        flows, members = [], []
        for j in range(s.ensemble):
            k_init, k_fit = jax.random.split(jax.random.fold_in(key, j))
            t0 = time.perf_counter()
            optimizer = optax.chain(optax.clip_by_global_norm(5.0), optax.adam(s.learning_rate))
            flow, losses = fit_to_data(
                k_fit,
                self._build(k_init, p, m),
                (z.astype(np.float32), xs.astype(np.float32)),
                optimizer=optimizer,
                max_epochs=s.max_epochs,
                max_patience=s.patience,
                batch_size=s.batch,
                val_prop=s.validation,
                show_progress=False,
            )
            val = [float(v) for v in losses["val"]]
            best = int(np.argmin(val))
            members.append(
                {
                    "epochs": len(val),
                    "best_epoch": best + 1,
                    "validation_loss": val[best],
                    "training_loss": float(losses["train"][best]),
                    "seconds": time.perf_counter() - t0,
                }
            )
            flows.append(flow)
        self._flows, self._tf, self._dims = flows, tf, (p, m)
        return {"pairs": n, "members": members}

    def sample(self, x, n: int, seed: int) -> np.ndarray:
        if self._flows is None:
            raise RuntimeError(f"amortised '{self.name}': sample before the estimator is trained or loaded")
        self._need()
        jax = _jax()
        x = np.atleast_2d(np.asarray(x, float))
        p, m = self._dims
        if x.shape[1] != m:
            raise ValueError(f"sample: the summaries have {x.shape[1]} values, the estimator was trained on {m}")
        cond = self._tf.summaries(x).astype(np.float32)
        k = len(self._flows)
        counts = [int(n) // k + (1 if j < int(n) % k else 0) for j in range(k)]
        key = jax.random.key(int(seed))
        parts = []
        for j, (flow, c) in enumerate(zip(self._flows, counts)):
            if c:
                z = np.asarray(_draw(flow, jax.random.fold_in(key, j), cond, c), float)  # (c, k, p)
                parts.append(np.transpose(z, (1, 0, 2)))
        z = np.concatenate(parts, axis=1)
        return self._tf.parameters(z.reshape(-1, p)).reshape(x.shape[0], int(n), p)

    # -------------------------------------------------------------------------- state
    def state(self) -> tuple[dict, bytes]:
        if self._flows is None:
            raise RuntimeError(f"amortised '{self.name}': nothing to save before the estimator is trained")
        import equinox as eqx

        buf = io.BytesIO()
        eqx.tree_serialise_leaves(buf, self._flows)
        p, m = self._dims
        return {"parameters": p, "summaries": m, "members": len(self._flows), **self._tf.meta()}, buf.getvalue()

    def load_state(self, meta: dict, blob: bytes) -> None:
        self._need()
        import equinox as eqx

        p, m, k = int(meta["parameters"]), int(meta["summaries"]), int(meta["members"])
        if k != self.settings.ensemble:
            raise ValueError(f"load_state: {k} flows in the file, the settings say ensemble = {self.settings.ensemble}")
        self._flows = eqx.tree_deserialise_leaves(io.BytesIO(blob), self._skeleton(p, m, k))
        self._tf, self._dims = _Transform.from_meta(meta), (p, m)

    def __getstate__(self):
        d = dict(self.__dict__)
        if self._flows is not None:  # the weights travel as bytes, rebuilt on arrival
            d["_flows"] = self.state()
        return d

    def __setstate__(self, d):
        saved = d.get("_flows")
        self.__dict__.update(d)
        if saved is not None:
            self._flows = None
            self.load_state(*saved)


def _draw(flow, key, cond, n: int):
    """``n`` draws of the standardised parameters for each row of ``cond`` (compiled once per shape)."""
    import equinox as eqx

    global _DRAW
    if _DRAW is None:
        _DRAW = eqx.filter_jit(lambda f, k, c, shape: f.sample(k, shape, condition=c))
    return _DRAW(flow, key, cond, (int(n),))


_DRAW = None
