"""Embedding maps (paper Fig. 5, 18, 19): 2-D t-SNE and PCA of the embedding of every recorded policy."""

import pathlib

import numpy as np
import torch as th

from sb3_pevfa.diagnostics.plotting import pyplot, save_figure
from sb3_pevfa.pevfa.off_policy import OffPolicyPeVFA
from sb3_pevfa.pevfa.records import PolicyRecord


def policy_embeddings(model, batch_size: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """(policy ids, embeddings ``(P, embedding_dim)``) of every policy in ``model.history``, by the current encoder
    in evaluation mode (SACPeVFA / TD3PeVFA: the critic's)."""
    policy, history = model.policy, model.history
    off_policy = isinstance(model, OffPolicyPeVFA)
    representation = policy.critic.representation if off_policy else policy.representation
    embed = representation if off_policy else policy.embed
    if representation.embedding_dim == 0:
        raise ValueError("representation='none' has no embedding to map")
    ids = np.array(history.policy_ids)
    if len(ids) < 3:
        raise ValueError(f"The history holds {len(ids)} policies; an embedding map needs at least 3")
    training = policy.training
    policy.set_training_mode(False)
    chunks = []
    with th.no_grad():
        for start in range(0, len(ids), batch_size):
            data = PolicyRecord.from_numpy(history.records(ids[start : start + batch_size]), model.device)
            chunks.append(embed(data).cpu().numpy())
    policy.set_training_mode(training)
    return ids, np.concatenate(chunks)


def embedding_map(embeddings: np.ndarray, method: str, seed: int = 0) -> np.ndarray:
    """2-D coordinates of the embeddings by ``"tsne"`` or ``"pca"`` (scikit-learn)."""
    if method == "pca":
        from sklearn.decomposition import PCA

        return PCA(n_components=2, random_state=seed).fit_transform(embeddings)
    if method == "tsne":
        from sklearn.manifold import TSNE

        perplexity = float(min(30, max(2, len(embeddings) // 4)))
        return TSNE(n_components=2, perplexity=perplexity, init="pca", random_state=seed).fit_transform(embeddings)
    raise ValueError(f"Unknown method {method!r}, valid choices: ('tsne', 'pca')")


def plot_embedding_maps(
    model, png: str | pathlib.Path, methods: tuple[str, ...] = ("tsne", "pca"), seed: int = 0
) -> pathlib.Path:
    """One row per method, coloured by the policy's return (``episode_return`` recorded in the history) and by its
    iteration (order of recording)."""
    plt = pyplot()

    ids, embeddings = policy_embeddings(model)
    returns = np.array([model.history.record_info(int(pid)).get("episode_return", np.nan) for pid in ids], dtype=float)
    fig, axes = plt.subplots(len(methods), 2, figsize=(10, 4.2 * len(methods)), squeeze=False)
    for row, method in zip(axes, methods):
        coordinates = embedding_map(embeddings, method, seed)
        for ax, (values, label) in zip(row, ((returns, "average return"), (ids, "iteration (policy id)"))):
            known = np.isfinite(values)
            points = ax.scatter(coordinates[known, 0], coordinates[known, 1], s=8, c=values[known], cmap="viridis")
            fig.colorbar(points, ax=ax, label=label)
            if not known.all():  # e.g. a policy whose rollout ended no episode has no return
                ax.scatter(coordinates[~known, 0], coordinates[~known, 1], s=8, c="lightgray", label=f"no {label} recorded")
                ax.legend(loc="best", fontsize=8)
            ax.set(title=f"{method.upper()} of {len(ids)} policies, by {label}", xticks=[], yticks=[])
    return save_figure(fig, png)
