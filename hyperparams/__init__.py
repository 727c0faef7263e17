"""
SOUP's hyper-parameters in the RL Zoo's format, installed as ``sb3_soup.hyperparams`` (setup.py maps this folder):

- ``soup.yml``: the defaults' entries, what ``python -m rl_zoo3.train --algo soup`` reads without ``--conf-file``;
- ``soup_paper.yml``: the paper's settings (Section 5), for reproducing it (the experiment runner's paper suites).

``sb3_soup.presets.hyperparams_file(name)`` gives the installed path of either.
"""
