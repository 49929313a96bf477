"""Experiment: perturbed argmax against the softmax, and learning to rank with Fenchel-Young.

Part 1 checks the Gumbel-max identity: the Gumbel-perturbed argmax over the simplex equals
softmax(theta / sigma), with an error that falls as 1/sqrt(M).
Part 2 learns a linear scoring model from rankings only: each query has items with features
X, the target is the ranking of X w_true + noise, and the model w is trained with Adam on the
perturbed Fenchel-Young loss over the permutahedron (Berthet et al., NeurIPS 2020, Sec. 5).
The rank correlation of the learned model's rankings with the targets on held-out queries
measures success.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from rsmooth import _checks, noise, perturbed, viz
from rsmooth.experiments import _protocol

METRICS_DOC = """metrics.json keys: softmax_error (dict sigma -> list over num_samples of the max
|perturbed argmax - softmax|), softmax_max_abs_error (at the largest num_samples),
num_samples; ranking_loss (training loss per step), ranking_test_spearman_initial and
ranking_test_spearman_final (mean Spearman correlation of predicted and target rankings on
held-out queries), ranking_test_exact_final (fraction of held-out rankings exactly right)."""


@dataclasses.dataclass(frozen=True)
class Config:
    num_items: int = _protocol.option(6, "Size of the simplex of the softmax comparison.", min=2)
    sigmas: tuple[float, ...] = _protocol.option(
        (0.25, 0.5, 1.0, 2.0), "Temperatures of the softmax comparison (Gumbel noise scales).", flag="sigma")
    num_samples_grid: tuple[int, ...] = _protocol.option(
        (10, 100, 1000, 10000), "Numbers of samples of the perturbed argmax in the softmax comparison.", flag="samples", min=1)
    rank_items: int = _protocol.option(8, "Items ranked per query.", min=2)
    rank_features: int = _protocol.option(5, "Features per item of the linear scoring model.", min=1)
    rank_label_noise: float = _protocol.option(0.1, "Std of the noise on the true scores that make the target rankings.", min=0.0)
    rank_train_queries: int = _protocol.option(256, "Training queries.", min=1)
    rank_test_queries: int = _protocol.option(256, "Held-out queries.", min=1)
    rank_batch: int = _protocol.option(32, "Queries per Adam step.", min=1)
    rank_steps: int = _protocol.option(300, "Adam steps of the ranking model.", min=1)
    rank_sigma: float = _protocol.option(0.5, "Noise scale of the perturbed ranking (Fenchel-Young loss).", above=0.0)
    rank_num_samples: int = _protocol.option(32, "Samples per perturbed ranking.", min=1)
    learning_rate: float = _protocol.option(0.05, "Adam's learning rate for the ranking model.", above=0.0)

    @classmethod
    def quick(cls) -> "Config":
        return cls(num_samples_grid=(10, 100, 1000), rank_steps=120)

    def __post_init__(self):
        _protocol.check_options(self)
        if not (self.sigmas and all(sigma > 0 for sigma in self.sigmas)):
            raise ValueError(f"sigmas must be positive (at least one), got {self.sigmas}")
        if not self.num_samples_grid:
            raise ValueError("num_samples_grid needs at least one number of samples")


def spearman(a, b):
    """Spearman correlation of two rank vectors (ranks 1..n without ties)."""
    n = a.shape[-1]
    return 1.0 - 6.0 * jnp.sum((a - b) ** 2, axis=-1) / (n * (n**2 - 1))


def _softmax_part(config: Config, key, bar) -> dict:
    theta = jax.random.normal(key, (config.num_items,))
    errors: dict = {}
    for sigma in config.sigmas:
        errors[str(sigma)] = []
        for m in config.num_samples_grid:
            key, sub = jax.random.split(key)
            y = perturbed.argmax(sub, theta, sigma=sigma, num_samples=m, noise=noise.Gumbel())
            errors[str(sigma)].append(float(jnp.max(jnp.abs(y - jax.nn.softmax(theta / sigma)))))
            bar.update()
    sigma_show = config.sigmas[len(config.sigmas) // 2]
    y_show = perturbed.argmax(key, theta, sigma=sigma_show, num_samples=config.num_samples_grid[-1])
    return {"errors": errors, "theta": theta, "y_show": y_show, "sigma_show": sigma_show}


def _ranking_data(config: Config, key, num_queries):
    k_x, k_noise = jax.random.split(key)
    x = jax.random.normal(k_x, (num_queries, config.rank_items, config.rank_features))
    return x, k_noise


def _ranking_part(config: Config, key, bar) -> dict:
    k_true, k_train, k_test, k_init, key = jax.random.split(key, 5)
    w_true = jax.random.normal(k_true, (config.rank_features,))

    def targets(x, k):
        scores = x @ w_true + config.rank_label_noise * jax.random.normal(k, x.shape[:2])
        return jax.vmap(perturbed.ranking_argmax)(scores)

    x_train, k = _ranking_data(config, k_train, config.rank_train_queries)
    y_train = targets(x_train, k)
    x_test, k = _ranking_data(config, k_test, config.rank_test_queries)
    y_test = targets(x_test, k)

    def loss_fn(w, xb, yb, k):
        keys = jax.random.split(k, xb.shape[0])
        losses = jax.vmap(
            lambda x, y, kk: perturbed.fenchel_young_loss(
                kk, x @ w, y, sigma=config.rank_sigma, num_samples=config.rank_num_samples,
                noise=noise.Gaussian(), oracle=perturbed.ranking_argmax,
            )
        )(xb, yb, keys)
        return jnp.mean(losses)

    optimizer = optax.adam(config.learning_rate)

    def step(w, opt_state, k):
        k_batch, k_loss = jax.random.split(k)
        idx = jax.random.choice(k_batch, config.rank_train_queries, (config.rank_batch,), replace=False)
        loss, grad = jax.value_and_grad(loss_fn)(w, x_train[idx], y_train[idx], k_loss)
        updates, opt_state = optimizer.update(grad, opt_state)
        return optax.apply_updates(w, updates), opt_state, loss

    step = _checks.jit_checked_on_host(step, "the ranking experiment's training step")
    def evaluate(w):
        predicted = jax.vmap(perturbed.ranking_argmax)(x_test @ w)
        return float(jnp.mean(spearman(predicted, y_test))), float(jnp.mean(jnp.all(predicted == y_test, axis=-1)))

    w = 0.1 * jax.random.normal(k_init, (config.rank_features,))
    opt_state = optimizer.init(w)
    initial, _ = evaluate(w)
    losses, curve = [], []
    for i in range(config.rank_steps):
        key, sub = jax.random.split(key)
        w, opt_state, loss = step(w, opt_state, sub)
        losses.append(float(loss))
        if i % 10 == 0 or i == config.rank_steps - 1:
            curve.append((i, evaluate(w)[0]))
        bar.update()
    final, exact = evaluate(w)
    cosine = float(w @ w_true / (jnp.linalg.norm(w) * jnp.linalg.norm(w_true)))
    return {"losses": losses, "curve": curve, "initial": initial, "final": final, "exact": exact, "cosine": cosine}


def run(config: Config, out: Path | str, key, progress: bool = True) -> dict:
    """Runs both parts, writes metrics.json and two PNG figures under `out`, returns metrics."""
    out = Path(out)
    k_soft, k_rank = jax.random.split(key)
    total = len(config.sigmas) * len(config.num_samples_grid) + config.rank_steps
    with tqdm(total=total, desc="perturbed-argmax", disable=not progress) as bar:
        soft = _softmax_part(config, k_soft, bar)
        rank = _ranking_part(config, k_rank, bar)

    fig, (ax_err, ax_bar) = viz.plt.subplots(1, 2, figsize=(11, 4))
    m_grid = np.asarray(config.num_samples_grid, float)
    for sigma, errs in soft["errors"].items():
        ax_err.loglog(m_grid, errs, "o-", label=f"sigma={sigma}")
    ax_err.loglog(m_grid, 0.5 / np.sqrt(m_grid), "k:", label=r"$0.5/\sqrt{M}$")
    ax_err.set_xlabel("samples M")
    ax_err.set_title("max |Gumbel-perturbed argmax - softmax|")
    ax_err.legend(fontsize=8)
    idx = np.arange(config.num_items)
    ax_bar.bar(idx - 0.2, soft["y_show"], 0.4, label=f"perturbed argmax (M={config.num_samples_grid[-1]})")
    ax_bar.bar(idx + 0.2, jax.nn.softmax(soft["theta"] / soft["sigma_show"]), 0.4, label="softmax")
    ax_bar.set_title(f"sigma={soft['sigma_show']}")
    ax_bar.legend(fontsize=8)
    fig.tight_layout()
    viz.save_figure(fig, out / "softmax.png")

    fig, (ax_loss, ax_corr) = viz.plt.subplots(1, 2, figsize=(11, 4))
    ax_loss.plot(rank["losses"])
    ax_loss.set_xlabel("Adam step")
    ax_loss.set_title("Fenchel-Young loss (perturbed ranking, minibatch)")
    steps, corr = zip(*rank["curve"])
    ax_corr.plot(steps, corr, "o-")
    ax_corr.set_ylim(-1, 1)
    ax_corr.set_xlabel("Adam step")
    ax_corr.set_title("held-out Spearman correlation of rankings")
    fig.tight_layout()
    viz.save_figure(fig, out / "ranking.png")

    metrics = {
        "num_samples": list(config.num_samples_grid),
        "softmax_error": soft["errors"],
        "softmax_max_abs_error": max(errs[-1] for errs in soft["errors"].values()),
        "ranking_loss": rank["losses"],
        "ranking_test_spearman_initial": rank["initial"],
        "ranking_test_spearman_final": rank["final"],
        "ranking_test_exact_final": rank["exact"],
        "ranking_weight_cosine": rank["cosine"],
    }
    viz.write_metrics(out / "metrics.json", metrics)
    return metrics


def summary(metrics: dict) -> dict:
    """The lines printed after a run: the softmax error and the held-out rank correlation."""
    return {
        "max |perturbed argmax - softmax|": round(metrics["softmax_max_abs_error"], 4),
        "held-out Spearman correlation, before -> after": (
            f"{metrics['ranking_test_spearman_initial']:.3f} -> {metrics['ranking_test_spearman_final']:.3f}"
        ),
    }


EXPERIMENT = _protocol.Experiment(
    command=("experiment", "perturbed-argmax"),
    name="perturbed-argmax",
    config=Config,
    run=run,
    summary=summary,
    help="Gumbel-perturbed argmax against the softmax, and learning to rank with the perturbed Fenchel-Young loss.",
    metrics_doc=METRICS_DOC,
)
