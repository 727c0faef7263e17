"""
SOUP's search space for the RL Zoo's optimiser (``python -m rl_zoo3.train --algo soup -optimize``), in the Zoo's
style (``rl_zoo3/hyperparams_opt.py``): ``sample_soup_params`` draws the values, ``convert_soup_params`` turns the
values optuna stores (``trial.params``) into SOUP's constructor arguments, so that ``--trial-id`` and ``load_trial``
rebuild exactly what a trial trained.
"""

from typing import Any

from sb3_soup.noise import DECAYING_NORMAL, zoo_action_noise

# Bodies and heads of actor (pi) and critic (qf); "paper" is SOUP's default (Section 5 of the paper). Each states where the
# action joins the critic as trials sampled before qf_action_layer joined the space trained it: at the second layer.
NET_ARCHS: dict[str, dict[str, Any]] = {
    "small": dict(pi_body=[64], pi_head=[64], qf_body=[64, 64], qf_head=[64], qf_action_layer=1),
    "paper": dict(pi_body=[256], pi_head=[128], qf_body=[256, 256], qf_head=[128], qf_action_layer=1),
    "big": dict(pi_body=[400], pi_head=[300], qf_body=[400, 300], qf_head=[300], qf_action_layer=1),
}
# Where the action joins the critic: at its input (0, SB3's and TD3's critic) or at the second body layer (1, the paper's)
QF_ACTION_LAYERS = (0, 1)
N_HEADS = (3, 5, 10)
CONFIDENCES = ("none", "fixed", "decayed", "adaptive", "ucb")
# The search space of the training scheme (a subset of what SOUP accepts, sb3_soup.arguments; an Optuna study cannot
# resume once a categorical's choices change, so a new choice joins only with a new space)
TRAIN_HEADS = ("active", "all_critics", "all")
TARGET_Q = ("own", "min_pair")
POLICY_DELAYS = (1, 2)
TARGET_POLICY_NOISES = (0.0, 0.2)
# What a trial sampled before 0.2.0 trained with: the search space had no delay and no smoothing, and SOUP's defaults
# were these (so that --trial-id rebuilds such a trial as it trained, whatever today's defaults)
SCHEME_BEFORE_0_2_0: dict[str, Any] = dict(policy_delay=1, target_policy_noise=0.0)


def convert_soup_params(sampled_params: dict[str, Any]) -> dict[str, Any]:
    """
    Turn sampled values into SOUP's arguments: ``one_minus_gamma`` -> ``gamma``, ``batch_size_pow`` ->
    ``batch_size``, ``net_arch`` name and ``qf_action_layer`` -> ``policy_kwargs`` (a trial without
    ``qf_action_layer``, sampled before it joined the space, trained the action at the critic's second layer, which
    :data:`NET_ARCHS` states), ``train_freq`` -> also ``gradient_steps`` (one gradient
    step per env-step, as in the Zoo's TD3 sampler), ``confidence_lr`` -> ``confidence_kwargs=dict(lr=...)`` (the
    adaptive confidence's learning rate), ``noise_std`` -> also ``noise_type="decaying_normal"`` (the RL Zoo's noise
    keys: the Zoo builds a constant :class:`sb3_soup.DecayingNormalActionNoise` from them, as SOUP's default is). A
    trial without ``policy_delay`` and ``target_policy_noise`` (sampled before 0.2.0) trained without delay and
    smoothing (:data:`SCHEME_BEFORE_0_2_0`): it is rebuilt so.

    :param sampled_params: the values of one trial (``trial.params``)
    :return: keyword arguments for ``SOUP``
    """
    hyperparams = dict(sampled_params)
    if "one_minus_gamma" in hyperparams:
        hyperparams["gamma"] = 1 - hyperparams.pop("one_minus_gamma")
    if "batch_size_pow" in hyperparams:
        hyperparams["batch_size"] = 2 ** hyperparams.pop("batch_size_pow")
    if "train_freq" in hyperparams:
        hyperparams["gradient_steps"] = hyperparams["train_freq"]
    if "net_arch" in hyperparams:
        net_arch = dict(NET_ARCHS[hyperparams.pop("net_arch")])
        if "qf_action_layer" in hyperparams:  # sampled since it joined the space; before, the arch's own (1)
            net_arch["qf_action_layer"] = hyperparams.pop("qf_action_layer")
        hyperparams["policy_kwargs"] = dict(net_arch=net_arch)
    if "confidence_lr" in hyperparams:
        hyperparams["confidence_kwargs"] = dict(lr=hyperparams.pop("confidence_lr"))
    if "noise_std" in hyperparams:  # the Zoo's keys (as --trial-id passes them on): a constant decaying_normal noise
        hyperparams["noise_type"] = DECAYING_NORMAL
    if "train_heads" in hyperparams:  # a trial of the scheme's search space: its delay and smoothing are stated
        hyperparams = {**SCHEME_BEFORE_0_2_0, **hyperparams}
    return hyperparams


def sample_soup_params(trial: Any, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """
    Sample SOUP hyper-parameters: the DDPG ones (actor and critic learning rates, batch size, tau, gamma, train
    frequency, network sizes, where the action joins the critic) and the ensemble's (number of heads, bootstrap mask
    probability, training scheme and targets, TD3's delay and target smoothing, confidence strategy and the adaptive
    confidence network's learning rate, exploration noise).

    :param trial: the optuna trial
    :param n_actions: size of the action space (of the exploration noise)
    :param n_envs: number of environments (unused)
    :param additional_args: the Zoo's extra arguments (HER settings; unused, SOUP's buffer is its own)
    :return: keyword arguments for ``SOUP``
    """
    params: dict[str, Any] = {
        "one_minus_gamma": trial.suggest_float("one_minus_gamma", 0.0001, 0.03, log=True),
        # 2**6 = 64 to 2**10 = 1024 (the paper's batch)
        "batch_size_pow": trial.suggest_int("batch_size_pow", 6, 10),
        "learning_rate": trial.suggest_float("learning_rate", 1e-5, 2e-3, log=True),
        "critic_learning_rate": trial.suggest_float("critic_learning_rate", 1e-5, 2e-3, log=True),
        "tau": trial.suggest_float("tau", 0.001, 0.08, log=True),
        "train_freq": trial.suggest_int("train_freq", 1, 10),
        "net_arch": trial.suggest_categorical("net_arch", list(NET_ARCHS)),
        "qf_action_layer": trial.suggest_categorical("qf_action_layer", list(QF_ACTION_LAYERS)),
        "n_heads": trial.suggest_categorical("n_heads", list(N_HEADS)),
        "mask_prob": trial.suggest_float("mask_prob", 0.3, 1.0),
        "noise_std": trial.suggest_float("noise_std", 0.05, 0.5),
        "train_heads": trial.suggest_categorical("train_heads", list(TRAIN_HEADS)),
        "target_q": trial.suggest_categorical("target_q", list(TARGET_Q)),
        "policy_delay": trial.suggest_categorical("policy_delay", list(POLICY_DELAYS)),
        "target_policy_noise": trial.suggest_categorical("target_policy_noise", list(TARGET_POLICY_NOISES)),
        "confidence": trial.suggest_categorical("confidence", list(CONFIDENCES)),
    }
    if params["confidence"] == "adaptive":
        params["confidence_lr"] = trial.suggest_float("confidence_lr", 1e-5, 1e-3, log=True)
    trial.set_user_attr("gamma", 1 - params["one_minus_gamma"])
    trial.set_user_attr("batch_size", 2 ** params["batch_size_pow"])
    # the Zoo passes the sampled values to the model as they are: the noise as the object its keys stand for
    return zoo_action_noise(convert_soup_params(params), (n_actions,))
