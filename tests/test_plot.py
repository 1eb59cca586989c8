"""experiments.plot: any metric against any swept parameter, faceted; the ROC panels wrapped."""

import matplotlib.image as mpimg
import pytest

from experiments.plot import main
from experiments.run import run
from harness_utils import small


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    """A little sweep: 2 methods x 2 SNRs, related maps, and one unrelated cell; 3 trials a cell."""
    root = tmp_path_factory.mktemp("sweep")
    for method in ("paper", "groth"):
        for snr in (10, 30):
            for unrelated in (False, True)[:1 + (method == "paper" and snr == 30)]:
                cfg = small(n_trials=3, n_jobs=1)
                cfg.matcher.method, cfg.matcher.taus = method, ["oracle", "chi2:0.01"]
                cfg.scenario.snr_db, cfg.scenario.unrelated = snr, unrelated
                run(cfg, root / "sweep" / f"{method}-{snr}-{unrelated}", root / "cache")
    return root / "sweep"


def test_a_metric_against_a_parameter_faceted_with_bands(sweep, tmp_path, capsys):
    out = tmp_path / "found.png"
    main([str(sweep), "--x", "snr_db", "--y", "found_rate", "--hue", "matcher.method", "-o", str(out)])
    # Unrelated pairs are drawn apart, on a row of their own, and said so.
    assert "related and unrelated map pairs drawn on rows of their own" in capsys.readouterr().err
    height, width, _ = mpimg.imread(out).shape
    assert height > width / 2 and out.with_suffix(".pdf").stat().st_size > 5_000
    # One panel per landmark count... only one here: a dimension that varies and is not mapped is refused.
    with pytest.raises(SystemExit) as exit_:
        main([str(sweep), "--x", "snr_db", "--y", "found_rate", "-o", str(tmp_path / "x.png")])
    assert exit_.value.code == 2
    assert "matcher.method takes several values (groth, paper): map it to --hue" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([str(sweep), "--x", "snr_db", "--y", "nonsense", "-o", str(tmp_path / "x.png")])
    assert "--y='nonsense' is invalid" in capsys.readouterr().err


def test_panels_wrap_onto_rows(sweep, tmp_path):
    one_row, wrapped = tmp_path / "row.png", tmp_path / "wrapped.png"
    common = [str(sweep), "--x", "snr_db", "--y", "success_rate", "--hue", "tau", "--where", "not scenario.unrelated",
              "--col", "matcher.method"]
    main([*common, "-o", str(one_row)])
    main([*common, "--wrap", "1", "-o", str(wrapped)])
    (h1, w1, _), (h2, w2, _) = mpimg.imread(one_row).shape, mpimg.imread(wrapped).shape
    assert w2 < 0.75 * w1 and h2 > 1.5 * h1


def test_roc_panels_wrap_and_name_the_unrelated_cells(sweep, tmp_path, capsys):
    out = tmp_path / "roc.png"
    main([str(sweep), "--kind", "roc", "--wrap", "1", "-o", str(out)])
    assert "1 unrelated-map cell(s) have no true pairs" in capsys.readouterr().err
    height, width, _ = mpimg.imread(out).shape
    assert height > width  # the one paper panel: linear and log rows
