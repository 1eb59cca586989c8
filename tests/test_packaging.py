"""The repository stands on its own: it installs anywhere and points nowhere outside itself."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _tracked_text_files():
    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    for name in out.splitlines():
        path = ROOT / name
        if path.suffix in {".py", ".md", ".yaml", ".toml", ".txt", ".cfg"} or path.name in {"Makefile", "run"}:
            if path.is_file() and path.stat().st_size < 2_000_000:
                yield name, path.read_text(errors="replace")


def test_nothing_refers_outside_the_repository():
    pattern = re.compile(r"\.\./shared|DESIGN(\.md| ?§)")
    offenders = [name for name, text in _tracked_text_files()
                 if pattern.search(text) and name != "tests/test_packaging.py"]
    assert offenders == []


def test_readme_starts_with_the_two_commands():
    text = (ROOT / "README.md").read_text()
    first_block = text.split("```")[1]
    assert "make paper" in first_block and "make test" in first_block
    ci = (ROOT / ".ci" / "run").read_text()
    assert "make test" in ci


def test_the_readme_example_prints_what_the_readme_shows(capsys):
    text = (ROOT / "README.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    shown = re.search(r"prints\n\n```\n(.*?)```", text, re.S).group(1)
    exec(code, {})
    assert capsys.readouterr().out == shown


def test_the_paper_is_cited_by_title():
    for doc in ("README.md", "docs/method.md"):
        text = (ROOT / doc).read_text()
        assert "Maximum likelihood fusion of stochastic maps" in text and "1303.6170" in text, doc


def test_a_wheel_installs_and_runs_a_sweep_from_elsewhere(tmp_path):
    """Not editable: the configs ship inside the package."""
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(tmp_path / "wheel"), str(ROOT)],
                   check=True, capture_output=True)
    wheel = next((tmp_path / "wheel").glob("mapmerge-*.whl"))
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(target), str(wheel)],
                   check=True, capture_output=True)
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": str(target)}
    proc = subprocess.run([sys.executable, "-c", "import experiments.run as r; print(r.CONF_DIR)"], cwd=work, env=env,
                          capture_output=True, text=True, check=True)
    assert Path(proc.stdout.strip()) == target / "experiments" / "conf"
    subprocess.run([sys.executable, "-m", "experiments.run", "-m", "experiment=smoke", "mc.n_trials=4",
                    "mc.chunk_size=2", "mc.examples=0", "mc.progress=false"], cwd=work, env=env, check=True,
                   capture_output=True)
    assert (work / "outputs" / "sweeps" / "smoke" / "aggregate" / "table.md").is_file()
    proc = subprocess.run([sys.executable, "-m", "mapmerge", "merge", "--help"], cwd=work, env=env,
                          capture_output=True, text=True, check=True)
    assert "--sigma" in proc.stdout


def test_import_mapmerge_leaves_heavy_modules_for_the_functions_that_need_them():
    # scipy.signal (about a second) serves only the exhaustive detector, pandas only map files:
    # a user's `import mapmerge` and every `mapmerge merge` call would pay for them otherwise.
    # OR-Tools, matplotlib and the harness's packages are extras: the core install has none of them.
    heavy = ("scipy.signal", "pandas", "ortools", "matplotlib", "hydra", "pyarrow")
    code = f"import sys, mapmerge; print(sorted(m for m in {heavy} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


#: Run the rest of the program as if only the core dependencies were installed.
_CORE_ONLY = """
import sys
class NotInstalled:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {"ortools", "matplotlib", "hydra", "omegaconf", "pyarrow", "tqdm", "astroalign",
                                  "pandas", "joblib"}:
            raise ModuleNotFoundError(f"No module named {name!r}")
sys.meta_path.insert(0, NotInstalled())
"""


def test_the_core_install_merges_map_files_and_names_the_extra_it_lacks(tmp_path):
    import numpy as np

    import mapmerge as mm

    for n, name in ((40, "small"), (400, "large")):
        sc = mm.simulate.make_pair(n, 0.75, 30, rng=0)
        for side, points in (("a", sc.p), ("b", sc.q)):
            np.savetxt(tmp_path / f"{name}_{side}.csv", points, delimiter=",", header="x,y", comments="")

    def merge(name, *options):
        code = _CORE_ONLY + "from mapmerge.cli import main; sys.exit(main(sys.argv[1:]))"
        return subprocess.run([sys.executable, "-c", code, "merge", f"{name}_a.csv", f"{name}_b.csv",
                               "--sigma", f"{sc.sigma}", "-o", f"{name}.csv", *options], cwd=tmp_path,
                              capture_output=True, text=True)

    proc = merge("small")
    assert proc.returncode == 0 and "matched" in proc.stdout, proc.stderr
    assert len((tmp_path / "small.csv").read_text().splitlines()) == 1 + 50  # 30 fused, 10 + 10 unshared
    # The paper method's LP on large maps is OR-Tools' min-cost flow: the extra [large].
    proc = merge("large", "--method", "paper")
    assert proc.returncode == 2 and proc.stderr.strip() == (
        "mapmerge: error: the LP of large maps (a min-cost flow) needs OR-Tools: pip install 'mapmerge[large]'")


def test_the_core_dependencies_are_numpy_and_scipy():
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    names = {re.match(r"[A-Za-z0-9_.-]+", requirement).group(0).lower() for requirement in project["dependencies"]}
    assert names == {"numpy", "scipy"}
    # What the core left out is still installable by name.
    extras = project["optional-dependencies"]
    assert any(r.startswith("pandas") for r in extras["dataframes"]) and any(r.startswith("joblib") for r in extras["parallel"])


def test_merging_two_map_files_loads_no_pandas_joblib_hydra_or_matplotlib(tmp_path):
    import numpy as np

    import mapmerge as mm

    sc = mm.simulate.make_pair(40, 0.75, 30, rng=1)
    for side, points in (("a", sc.p), ("b", sc.q)):
        np.savetxt(tmp_path / f"{side}.csv", points, delimiter=",", header="x,y", comments="")
    heavy = ("pandas", "joblib", "hydra", "matplotlib")
    code = ("import sys; from mapmerge.cli import main; "
            f"code = main(['merge', 'a.csv', 'b.csv', '--sigma', '{sc.sigma}', '-o', 'out.csv']); "
            f"print(code, sorted(m for m in {heavy} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=True).stdout
    assert out.splitlines()[-1] == "0 []"
    assert (tmp_path / "out.csv").read_text().startswith("x,y,origin,index_p,index_q,sxx,sxy,syy\n")


def test_every_module_is_an_attribute_of_the_package():
    """``mm.datasets`` works like ``mm.simulate`` (loaded on first use), and a typo is still an AttributeError."""
    import mapmerge as mm

    assert callable(mm.datasets.victoria_park) and callable(mm.plotting.plot_merge)
    assert callable(mm.search.search_pairs) and callable(mm.consensus.consensus_merge)
    with pytest.raises(AttributeError, match="has no attribute 'datasetz'"):
        mm.datasetz
