"""Print a SB3 test file with SOUP added wherever TD3 (or DDPG) is listed as an algorithm, or compared with as one
(``model_class == TD3`` becomes ``model_class in (TD3, SOUP)``: SOUP gets TD3's settings and checks); see build.sh."""

import ast
import sys

ALGOS = ("TD3", "DDPG")
path = sys.argv[1]
source = open(path).read()
lines = source.splitlines(keepends=True)
offsets = [0]
for line in lines:
    offsets.append(offsets[-1] + len(line))


def pos(lineno, col):
    return offsets[lineno - 1] + len(lines[lineno - 1].encode()[:col].decode())


def is_algo(node):
    return isinstance(node, ast.Name) and node.id in ALGOS


edits = []  # (start, end, text): text[start:end] becomes text (an insertion where start == end)
tree = ast.parse(source)
for node in ast.walk(tree):
    if isinstance(node, (ast.List, ast.Set, ast.Tuple)) and node.elts and all(isinstance(e, ast.Name) for e in node.elts):
        first = next((e for e in node.elts if is_algo(e)), None)
        if first is not None and not any(isinstance(e, ast.Name) and e.id == "SOUP" for e in node.elts):
            end = pos(first.end_lineno, first.end_col_offset)
            edits.append((end, end, ", SOUP"))
    elif isinstance(node, ast.Dict):
        for key, value in zip(node.keys, node.values):
            if is_algo(key):  # {TD3: 400} -> {TD3: 400, SOUP: 400}
                segment = ast.get_source_segment(source, value)
                end = pos(value.end_lineno, value.end_col_offset)
                edits.append((end, end, f", SOUP: {segment}"))
                break
            if isinstance(value, ast.Tuple) and value.elts and is_algo(value.elts[0]) and isinstance(key, ast.Constant):
                # {"td3": (TD3, "Pendulum-v1")} -> also {"soup": (SOUP, "Pendulum-v1")}
                rest = "".join(", " + ast.get_source_segment(source, e) for e in value.elts[1:])
                end = pos(value.end_lineno, value.end_col_offset)
                edits.append((end, end, f', "soup": (SOUP{rest})'))
                break
    elif isinstance(node, ast.Compare) and len(node.ops) == 1 and isinstance(node.ops[0], (ast.Eq, ast.NotEq)):
        # `model_class == TD3` (TD3's own settings or checks) -> `model_class in (TD3, SOUP)`
        right = node.comparators[0]
        if is_algo(right):
            start = pos(node.left.end_lineno, node.left.end_col_offset)
            end = pos(right.end_lineno, right.end_col_offset)
            op = "in" if isinstance(node.ops[0], ast.Eq) else "not in"
            edits.append((start, end, f" {op} ({right.id}, SOUP)"))
text = source
for start, end, piece in sorted(edits, reverse=True):
    text = text[:start] + piece + text[end:]
# the import, after the stable_baselines3 import of the algorithms
out, done = [], False
for line in text.splitlines(keepends=True):
    out.append(line)
    if not done and line.startswith("from stable_baselines3 import"):
        # (a parenthesised import spans lines: put ours after the whole statement)
        done = True
        if "(" in line and ")" not in line:
            done = "pending"
    elif done == "pending" and ")" in line:
        done = True
        out.append("from sb3_soup import SOUP\n")
        continue
    if done is True and out[-1] is line and line.startswith("from stable_baselines3 import"):
        out.append("from sb3_soup import SOUP\n")
text = "".join(out)
if "from sb3_soup import SOUP" not in text:
    text = "from sb3_soup import SOUP\n" + text
sys.stdout.write(text)
