"""A faster step: the compiled hash grid (same values, same gradients, deterministic, clean fallback), the L-inf
scene contraction without torch's max norm (bit-identical), the proposal networks' detached positions, and
``moisst-bench --speed``'s table."""

import pytest
import torch
from nerfstudio.field_components.encodings import HashEncoding

from moisst_ns import compiled_grid
from moisst_ns.bench.speed import speed_markdown
from moisst_ns.contraction import LinfSceneContraction, use_linf_contraction
from moisst_ns.model import _detached_positions


def _encodings():
    torch.manual_seed(0)
    return [HashEncoding(num_levels=4, min_res=4, max_res=64, log2_hashmap_size=10, implementation="torch"),
            HashEncoding(num_levels=3, min_res=8, max_res=32, log2_hashmap_size=8, implementation="torch")]


def _values_and_grads(encoding, x, g):
    encoding.hash_table.grad = None
    x = x.clone().requires_grad_(True)
    out = encoding(x)
    (out * g).sum().backward()
    return out.detach(), encoding.hash_table.grad.clone(), x.grad.clone()


def test_compiled_hash_grid_equals_nerfstudios_eager_one_and_repeats_bit_for_bit():
    if compiled_grid.cpp_compiler() is None:
        pytest.skip("no C++ compiler: the fallback test covers this machine")
    deterministic = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    eager, compiled = _encodings(), _encodings()
    try:
        assert compiled_grid.compile_hash_encodings(compiled) is None
        assert torch.are_deterministic_algorithms_enabled()
        for enc_e, enc_c in zip(eager, compiled):
            assert "pytorch_fwd" in enc_c.__dict__ and "pytorch_fwd" not in enc_e.__dict__
            for n in (1000, 777):  # dynamic shapes: a second batch size needs no new graph to be right
                x = torch.rand(n, 3, generator=torch.Generator().manual_seed(n))
                g = torch.randn(n, enc_e.get_out_dim(), generator=torch.Generator().manual_seed(n + 1))
                out_e, table_e, x_e = _values_and_grads(enc_e, x, g)
                out_c, table_c, x_c = _values_and_grads(enc_c, x, g)
                torch.testing.assert_close(out_c, out_e, rtol=0, atol=1e-6)
                torch.testing.assert_close(table_c, table_e, rtol=0, atol=1e-5)
                torch.testing.assert_close(x_c, x_e, rtol=1e-5, atol=1e-5)
                again = _values_and_grads(enc_c, x, g)
                assert all(torch.equal(a, b) for a, b in zip(again, (out_c, table_c, x_c)))
    finally:
        torch.use_deterministic_algorithms(deterministic[0], warn_only=deterministic[1])


@pytest.mark.parametrize("case, reason", [("no compiler", "no C++ compiler"), ("cuda", "compiled only on CPU"), ("none", "no torch hash-grid")])
def test_hash_grid_stays_eager_with_a_one_line_reason(monkeypatch, case, reason):
    encodings = _encodings()
    if case == "no compiler":
        monkeypatch.setattr(compiled_grid, "cpp_compiler", lambda: None)
    why = compiled_grid.compile_hash_encodings([] if case == "none" else encodings, "cuda" if case == "cuda" else "cpu")
    assert reason in why and "\n" not in why
    assert all("pytorch_fwd" not in e.__dict__ for e in encodings)


def test_hash_grid_compile_failure_falls_back_to_eager(monkeypatch):
    encodings = _encodings()
    deterministic = torch.are_deterministic_algorithms_enabled()

    def broken(encoding):
        def fail(x):
            raise RuntimeError("inductor: compilation failed\nlong log")
        return fail

    monkeypatch.setattr(compiled_grid, "cpp_compiler", lambda: "/usr/bin/g++")
    monkeypatch.setattr(compiled_grid, "_compiled_forward", broken)
    why = compiled_grid.compile_hash_encodings(encodings)
    assert why == "torch.compile failed (RuntimeError: inductor: compilation failed)"
    assert all("pytorch_fwd" not in e.__dict__ for e in encodings)
    assert torch.are_deterministic_algorithms_enabled() == deterministic
    x = torch.rand(10, 3)
    assert encodings[0](x).shape == (10, 8)


def test_linf_contraction_equals_nerfstudios_bit_for_bit_ties_included():
    from nerfstudio.field_components.spatial_distortions import SceneContraction

    x = torch.randn(4000, 3, generator=torch.Generator().manual_seed(0)) * 2
    x[:8] = torch.tensor([1.5, -1.5, 0.3])  # two components tie for the max: the gradient is shared between them
    x[8:16] = torch.tensor([2.0, 2.0, -2.0])
    x[16] = torch.tensor([1.0, 0.5, 0.2])  # on the unit cube's face
    assert bool((x.abs().amax(-1) < 1).any()) and bool((x.abs().amax(-1) > 1).any())
    g = torch.randn(4000, 3, generator=torch.Generator().manual_seed(1))
    results = []
    for contraction in (SceneContraction(order=float("inf")), LinfSceneContraction()):
        xx = x.clone().requires_grad_(True)
        y = contraction(xx)
        (y * g).sum().backward()
        results.append((y.detach(), xx.grad))
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])
    assert float(results[1][0].abs().max()) < 2.0


def test_model_fields_use_the_linf_contraction_and_other_contractions_are_left_alone():
    from nerfstudio.field_components.spatial_distortions import SceneContraction

    class Holder(torch.nn.Module):
        def __init__(self, distortion):
            super().__init__()
            self.spatial_distortion = distortion

    shared = SceneContraction(order=float("inf"))
    model = torch.nn.ModuleList([Holder(shared), Holder(shared), Holder(SceneContraction()), Holder(None)])
    assert use_linf_contraction(model) == 2
    assert type(model[0].spatial_distortion) is LinfSceneContraction and model[0].spatial_distortion is model[1].spatial_distortion
    assert type(model[2].spatial_distortion) is SceneContraction and model[3].spatial_distortion is None


def test_proposal_density_sees_positions_without_their_gradient():
    weights = torch.tensor([1.0, 2.0, 3.0], requires_grad=True)
    density = _detached_positions(lambda positions, times=None: (positions * weights).sum(-1, keepdim=True))
    positions = torch.rand(5, 3, requires_grad=True)
    out = density(positions)
    out.sum().backward()
    assert positions.grad is None  # the calibration behind the positions gets nothing from the proposal networks
    torch.testing.assert_close(weights.grad, positions.detach().sum(0))  # the network itself still learns


def test_speed_table_has_the_ratios_of_the_measured_figures():
    result = {"presets": {"moisst-lite": {"s_per_step": 0.15, "nerfacto_s_per_step": 0.3, "ratio": 0.5, "s_per_step_lidar": 0.18,
                                          "ratio_lidar": 0.6, "setup_s": {"nerfacto": 4.0, "cameras": 30.4, "lidar": 5.6}, "steps_timed": 40}}}
    lines = speed_markdown(result).splitlines()
    assert len(lines) == 3
    assert lines[2] == "| moisst-lite (40 steps timed) | 0.150 | 0.300 | 0.50 | 0.180 | 0.60 | 4 / 30 / 6 |"


def test_speed_section_survives_a_rewritten_benchmarks_page_and_takes_a_new_table():
    from moisst_ns.bench.speed import keep_speed_block, with_speed_table

    old_table = "| preset | MOISST s/step (cameras) | x |\n| --- | --- | --- |\n| moisst-lite | 0.2 | y |"
    old = f"# Benchmarks\n\n<!-- speed -->\n## Speed\n\nProse.\n\n{old_table}\n\nMore prose.\n<!-- /speed -->\n## Table I\nold\n"
    new = keep_speed_block(old, "# Benchmarks (quick)\n\n## Table I\nnew\n")
    assert new == "# Benchmarks (quick)\n\n<!-- speed -->\n## Speed\n\nProse.\n\n" + old_table + "\n\nMore prose.\n<!-- /speed -->\n\n## Table I\nnew\n"
    table = "| preset | MOISST s/step (cameras) | z |\n| --- | --- | --- |\n| moisst | 3.0 | w |"
    updated = with_speed_table(new, table)
    assert updated == new.replace(old_table, table)  # only the table changes, the prose stays
    assert with_speed_table("# B\nbody\n", table) == f"# B\n\n<!-- speed -->\n## Speed\n\n{table}\n<!-- /speed -->\nbody\n"
    assert keep_speed_block("no block", "# T\nx") == "# T\nx"
