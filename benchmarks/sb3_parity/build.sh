#!/usr/bin/env bash
# SB3's own off-policy tests with SOUP added next to TD3/DDPG (issue 18's measure of the drop-in), built outside this
# repository (SB3's files stay theirs, they are not committed here): the tests/ of a Stable-Baselines3 git checkout,
# with SOUP added to every algorithm list, set, tuple and dict (same value as TD3's) by add_soup.py; every argument as
# SB3 wrote it. Then run the SOUP cases:
#
#   git clone https://github.com/DLR-RM/stable-baselines3 /tmp/sb3 && git -C /tmp/sb3 checkout v2.9.2  # the installed SB3
#   bash benchmarks/sb3_parity/build.sh /tmp/sb3/.git /tmp/sb3-parity
#   cd /tmp/sb3-parity && PYTHONHASHSEED=0 OMP_NUM_THREADS=1 PYTHONPATH=/path/to/sb3-soup \
#       python -m pytest -n 0 -q -p no:cacheprovider -rfEs tests -k SOUP
#
# Usage: bash benchmarks/sb3_parity/build.sh SB3_GIT_DIR OUT
set -euo pipefail
GIT_DIR=${1:?the .git folder of a stable-baselines3 checkout}
OUT=${2:?the folder to build the harness in (outside this repository)}
HERE=$(cd "$(dirname "$0")" && pwd)
SRC=$(mktemp -d)
trap 'rm -rf "$SRC"' EXIT
rm -rf "$OUT/tests"
mkdir -p "$OUT/tests"
git --git-dir="$GIT_DIR" archive HEAD tests | tar -x -C "$SRC"
git --git-dir="$GIT_DIR" log -1 --format='%H %cd' > "$OUT/SB3_COMMIT"
FILES="test_run test_save_load test_callbacks test_vec_normalize test_dict_env test_her test_predict test_deterministic
test_spaces test_train_eval_mode test_cnn test_custom_policy test_tensorboard test_identity test_n_step_replay"
cp "$SRC/tests/__init__.py" "$OUT/tests/" 2>/dev/null || touch "$OUT/tests/__init__.py"
[ -f "$SRC/tests/conftest.py" ] && cp "$SRC/tests/conftest.py" "$OUT/tests/"
for name in $FILES; do
    python3 "$HERE/add_soup.py" "$SRC/tests/$name.py" > "$OUT/tests/$name.py"
done
echo "built $(ls "$OUT/tests" | wc -l) files from $(cat "$OUT/SB3_COMMIT")"
# SB3's pytest settings (its pyproject.toml's [tool.pytest.ini_options]: markers, filterwarnings)
git --git-dir="$GIT_DIR" show HEAD:pyproject.toml | python3 -c "
import sys, tomllib
options = tomllib.loads(sys.stdin.read())['tool']['pytest']['ini_options']
print('[pytest]')
for key in ('filterwarnings', 'markers'):
    print(key + ' =')
    for value in options[key]:
        print('    ' + value)
" > "$OUT/pytest.ini"
