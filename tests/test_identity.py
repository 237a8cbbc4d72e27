"""Identity fusion (Challa & Koks, seed 004): Bayes (eqs. 35-41, Tables 1-2) and Dempster-Shafer
(eqs. 43-47, Tables 3-4, support and plausibility)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from fusionlog.core.identity.dempster import conjunctive
from fusionlog.identity import (
    MASS_TOL,
    array_to_mass,
    bayes_fusion,
    bayes_fusion_posteriors,
    belief,
    belief_array,
    dempster_combine,
    dempster_combine_array,
    mass_to_array,
    plausibility,
    plausibility_array,
    subset_index,
)

HYPO = settings(max_examples=60, deadline=None)

# ---------------------------------------------------------------------------------------------
# The paper's aircraft example
# ---------------------------------------------------------------------------------------------

CLASSES = ("Learjet", "Falcon", "Caravan")
LEARJET = frozenset({"Learjet"})
FALCON = frozenset({"Falcon"})
CARAVAN = frozenset({"Caravan"})
FAST = frozenset({"Learjet", "Falcon"})  # Sec. 4.1 (2)
UNKNOWN = frozenset(CLASSES)  # Sec. 4.1 (1): the whole frame, cf. eq. (51)
ROWS = {"Learjet": LEARJET, "Falcon": FALCON, "Caravan": CARAVAN, "Fast": FAST, "Unknown": UNKNOWN}

# Table 1: sensors' old data (x | Y_0^i), new data (x | Y_1^i), fusion node's (x | Y_0^1 Y_0^2).
T1_OLD = [[0.4, 0.4, 0.2], [0.6, 0.3, 0.1]]
T1_NEW = [[0.70, 0.29, 0.01], [0.80, 0.15, 0.05]]
T1_NODE = [0.5, 0.4, 0.1]
# Table 2 / eq. (40) "New value", as printed (percent).
T2_NEW_VALUE = {"Learjet": "88.8", "Falcon": "11.0", "Caravan": "0.2"}

# Tables 3 and 4: (sensor 1, sensor 2, fused) in percent, as printed. Table 4 leaves sensor 2's
# "Fast" blank; the text says it "assigns no mass at all", i.e. 0.
TABLE3 = {
    "Learjet": ("30", "40", "55"),
    "Falcon": ("15", "10", "16"),
    "Caravan": ("3", "2", "0.4"),
    "Fast": ("42", "45", "29"),
    "Unknown": ("10", "3", "0.3"),
}
TABLE4 = {
    "Learjet": ("30", "50", "63"),
    "Falcon": ("15", "30", "31"),
    "Caravan": ("3", "17", "3.5"),
    "Fast": ("42", "0", "2"),
    "Unknown": ("10", "3", "0.5"),
}


def _as_printed(fraction: float, printed: str) -> str:
    """Round a fraction to a percentage with as many decimals as the printed entry has."""
    decimals = len(printed.partition(".")[2])
    return f"{100 * fraction:.{decimals}f}"


def _table_inputs(table: dict) -> tuple[dict, dict]:
    m1 = {ROWS[row]: float(s1) / 100 for row, (s1, _, _) in table.items()}
    m2 = {ROWS[row]: float(s2) / 100 for row, (_, s2, _) in table.items()}
    return m1, m2


# ---------------------------------------------------------------------------------------------
# Bayes: eqs. (38)-(41), Tables 1-2
# ---------------------------------------------------------------------------------------------


def test_table2_reproduced_from_table1():
    fused = bayes_fusion_posteriors(T1_NEW, T1_OLD, T1_NODE)
    got = {c: _as_printed(p, T2_NEW_VALUE[c]) for c, p in zip(CLASSES, fused, strict=True)}
    assert got == T2_NEW_VALUE
    assert fused.sum() == pytest.approx(1.0, abs=1e-15)
    np.testing.assert_allclose(fused, [0.887761572, 0.110336081, 0.001902346], atol=1e-9)


def test_eq39_unnormalised_terms():
    # eq. (39): 0.70*0.80*0.5/(0.4*0.6), 0.29*0.15*0.4/(0.4*0.3), 0.01*0.05*0.1/(0.2*0.1).
    terms = np.array([0.28 / 0.24, 0.0174 / 0.12, 0.00005 / 0.02])
    fused = bayes_fusion_posteriors(T1_NEW, T1_OLD, T1_NODE)
    np.testing.assert_allclose(fused, terms / terms.sum(), rtol=1e-12)


def test_table2_needs_the_sensors_old_data():
    # Table 2 alone (node prior and latest sensor probabilities) does not give its last column:
    # without dividing out the sensors' own priors (Table 1, old data) Learjet would be 94.1 %.
    naive = bayes_fusion(T1_NEW, T1_NODE)
    assert _as_printed(naive[0], "88.8") == "94.1"


def test_bayes_fusion_equals_posterior_form_with_likelihood_ratios():
    lik = np.asarray(T1_NEW) / np.asarray(T1_OLD)
    np.testing.assert_allclose(
        bayes_fusion(lik, T1_NODE), bayes_fusion_posteriors(T1_NEW, T1_OLD, T1_NODE), rtol=1e-14
    )


def test_eq41_three_sensors_order_irrelevant():
    post = np.array([[0.70, 0.29, 0.01], [0.80, 0.15, 0.05], [0.5, 0.3, 0.2]])
    old = np.array([[0.4, 0.4, 0.2], [0.6, 0.3, 0.1], [0.3, 0.3, 0.4]])
    node = np.array([0.5, 0.4, 0.1])
    expected = post.prod(0) * node / old.prod(0)
    expected /= expected.sum()
    for perm in itertools.permutations(range(3)):
        p = list(perm)
        np.testing.assert_allclose(bayes_fusion_posteriors(post[p], old[p], node), expected)


def test_bayes_batch_runs_steps():
    rng = np.random.default_rng(4)
    lik = rng.uniform(0.0, 1.0, (50, 7, 3, 4))  # runs, steps, sensors, classes
    prior = rng.dirichlet(np.ones(4), (50, 7))
    fused = bayes_fusion(lik, prior)
    assert fused.shape == (50, 7, 4)
    for r, k in [(0, 0), (13, 5), (49, 6)]:
        np.testing.assert_allclose(fused[r, k], bayes_fusion(lik[r, k], prior[r, k]), rtol=1e-13)
    # A prior shared by all runs broadcasts.
    assert bayes_fusion(lik, prior[0, 0]).shape == (50, 7, 4)


def test_bayes_many_small_likelihoods_do_not_underflow():
    lik = np.full((400, 2), 1e-5)
    lik[:, 0] *= 2.0
    fused = bayes_fusion(lik, [0.5, 0.5])
    assert fused[0] == pytest.approx(1.0) and np.isfinite(fused).all()


_probs = st.integers(2, 6).flatmap(
    lambda c: st.lists(st.floats(0.01, 1.0), min_size=c, max_size=c).map(np.array)
)


@HYPO
@given(_probs)
def test_bayes_one_sensor_uniform_prior_is_normalised_likelihood(lik):
    fused = bayes_fusion(lik[None, :], np.full(lik.size, 1.0 / lik.size))
    np.testing.assert_allclose(fused, lik / lik.sum(), rtol=1e-12)


@HYPO
@given(st.integers(2, 5), st.integers(1, 4), st.integers(1, 6), st.integers(0, 2**32 - 1))
def test_bayes_batch_equals_items_and_sequential(c, s, batch, seed):
    rng = np.random.default_rng(seed)
    lik = rng.uniform(0.01, 1.0, (batch, s, c))
    prior = rng.dirichlet(np.ones(c), batch)
    fused = bayes_fusion(lik, prior)
    for b in range(batch):
        np.testing.assert_allclose(fused[b], bayes_fusion(lik[b], prior[b]), rtol=1e-12)
        # Fusing the sensors one at a time, feeding each result back as the prior, is the same.
        seq = prior[b]
        for i in range(s):
            seq = bayes_fusion(lik[b, i : i + 1], seq)
        np.testing.assert_allclose(fused[b], seq, rtol=1e-10)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: bayes_fusion([[0.5, -0.1]], [0.5, 0.5]), "non-negative"),
        (lambda: bayes_fusion([[0.5, np.nan]], [0.5, 0.5]), "finite"),
        (lambda: bayes_fusion([0.5, 0.5], [0.5, 0.5]), "sensors, classes"),
        (lambda: bayes_fusion([[0.5, 0.5]], [0.3, 0.3, 0.4]), "classes"),
        (lambda: bayes_fusion([[1.0, 0.0]], [0.0, 1.0]), "zero for every class"),
        (
            lambda: bayes_fusion_posteriors(T1_NEW, [[0.4, 0.6, 0.0], T1_OLD[1]], T1_NODE),
            "strictly",
        ),
        (lambda: bayes_fusion_posteriors(T1_NEW, [[0.5, 0.5]] * 2, T1_NODE), "broadcast"),
    ],
)
def test_bayes_errors(call, message):
    with pytest.raises(ValueError, match=message) as info:
        call()
    assert "\n" not in str(info.value)


# ---------------------------------------------------------------------------------------------
# Dempster's rule: eqs. (45)-(47), Tables 3-4
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("table", [TABLE3, TABLE4], ids=["table3", "table4"])
def test_dempster_tables_reproduced(table):
    m1, m2 = _table_inputs(table)
    fused, conflict = dempster_combine(m1, m2)
    got = {
        row: _as_printed(fused.get(ROWS[row], 0.0), printed) for row, (*_, printed) in table.items()
    }
    assert got == {row: printed for row, (*_, printed) in table.items()}
    assert sum(fused.values()) == pytest.approx(1.0, abs=1e-15)  # "Total mass 100 %"
    assert set(fused) <= set(ROWS.values())
    assert 0.0 < conflict < 1.0


def test_table3_relative_masses_and_conflict():
    # eq. (46): the Learjet's relative (unnormalised) mass 0.472, printed as 0.47; the others
    # "are found similarly"; K = 1 - their sum.
    m1, m2 = _table_inputs(TABLE3)
    relative = {LEARJET: 0.472, FALCON: 0.139, CARAVAN: 0.0035, FAST: 0.2466, UNKNOWN: 0.003}
    assert f"{relative[LEARJET]:.2f}" == "0.47"
    fused, conflict = dempster_combine(m1, m2)
    assert conflict == pytest.approx(1 - sum(relative.values()), abs=1e-15)
    for key, value in relative.items():
        assert fused[key] == pytest.approx(value / sum(relative.values()), rel=1e-12)
    _, conflict4 = dempster_combine(*_table_inputs(TABLE4))
    assert conflict4 == pytest.approx(0.3369, abs=1e-15)


def test_unknown_is_the_whole_frame():
    # Sec. 4.1 prints Unknown as "{Learjet, Falcon,}"; only Unknown = {Learjet, Falcon, Caravan}
    # (eq. 51: {Learjet} cap Unknown = {Learjet}) reproduces the Caravan entry of Table 3.
    m1, m2 = _table_inputs(TABLE3)
    fused, _ = dempster_combine(m1, m2, frame=CLASSES)
    assert _as_printed(fused[CARAVAN], "0.4") == "0.4"
    relative_caravan = 0.03 * 0.02 + 0.03 * 0.03 + 0.10 * 0.02  # C.C + C.U + U.C
    assert fused[CARAVAN] == pytest.approx(relative_caravan / 0.8641, rel=1e-12)


def test_support_and_plausibility_of_table3_fusion():
    # The text after eq. (47) (its support/plausibility table is not in the seed text): a good
    # possibility of a Learjet, a reasonable chance of a Falcon, almost no chance of a Caravan,
    # virtual certainty that the aircraft is fast, and 100 % for "Unknown".
    fused, _ = dempster_combine(*_table_inputs(TABLE3), frame=CLASSES)
    bel = {row: belief(fused, s, CLASSES) for row, s in ROWS.items()}
    pl = {row: plausibility(fused, s, CLASSES) for row, s in ROWS.items()}
    for row in ROWS:
        assert bel[row] <= pl[row]
    expected = {  # computed from the fused masses of Table 3 (Bel, Pl)
        "Learjet": (0.546233, 0.835089),
        "Falcon": (0.160861, 0.449716),
        "Caravan": (0.004050, 0.007522),
        "Fast": (0.992478, 0.995950),
        "Unknown": (1.0, 1.0),
    }
    for row, (b, p) in expected.items():
        assert (bel[row], pl[row]) == pytest.approx((b, p), abs=1e-6)
    assert bel["Learjet"] > bel["Falcon"] > bel["Caravan"]
    assert pl["Learjet"] > pl["Falcon"] > pl["Caravan"]
    assert pl["Caravan"] < 0.01  # almost no chance
    assert bel["Fast"] > 0.99  # virtual certainty that it is fast
    assert bel["Fast"] == pytest.approx(1 - pl["Caravan"])  # Bel(A) = 1 - Pl(not A)
    assert pl["Fast"] == pytest.approx(1 - bel["Caravan"])
    assert bel["Unknown"] == pytest.approx(1.0) and pl["Unknown"] == pytest.approx(1.0)
    # Table 4's fusion "still lead[s] to the same belief as previously" (same ordering).
    fused4, _ = dempster_combine(*_table_inputs(TABLE4), frame=CLASSES)
    bel4 = [belief(fused4, ROWS[r]) for r in ("Learjet", "Falcon", "Caravan")]
    assert bel4[0] > bel4[1] > bel4[2]
    assert belief(fused4, FAST) > 0.95


@HYPO
@given(st.floats(0, 1), st.floats(0, 1), st.floats(0, 1), st.floats(0, 1))
def test_eq44_zou_occupancy(a, b, c, d):
    # Frame {O, E}, U = {O, E}: eq. (44) for m(O).
    assume(1 - a - b >= 0 and 1 - c - d >= 0)
    O, E, U = frozenset("O"), frozenset("E"), frozenset("OE")
    ms = {O: a, E: b, U: 1 - a - b}
    mo = {O: c, E: d, U: 1 - c - d}
    denominator = 1 - a * d - b * c
    assume(denominator > 1e-9)
    fused, conflict = dempster_combine(ms, mo)
    expected = (a * c + a * (1 - c - d) + (1 - a - b) * c) / denominator
    assert fused.get(O, 0.0) == pytest.approx(expected, rel=1e-9, abs=1e-12)
    assert conflict == pytest.approx(a * d + b * c, abs=1e-12)


def test_array_api_matches_dict_api_and_bitmasks():
    m1, m2 = _table_inputs(TABLE3)
    a1, a2 = mass_to_array(m1, CLASSES), mass_to_array(m2, CLASSES)
    assert subset_index(FAST, CLASSES) == 0b011 and subset_index(UNKNOWN, CLASSES) == 0b111
    assert a1[0b001] == 0.30 and a1[0b011] == 0.42 and a1[0] == 0
    masses, conflict = dempster_combine_array(a1, a2)
    fused, k = dempster_combine(m1, m2, frame=CLASSES)
    assert array_to_mass(masses, CLASSES) == pytest.approx(fused)
    assert float(conflict) == k
    assert belief_array(masses, 0b011) == pytest.approx(belief(fused, FAST))
    assert plausibility_array(masses, 0b001) == pytest.approx(plausibility(fused, LEARJET))


def test_dempster_three_way_conflict():
    m1, m2 = _table_inputs(TABLE3)
    m3 = {LEARJET: 0.2, CARAVAN: 0.5, UNKNOWN: 0.3}
    fused, k = dempster_combine(m1, m2, m3)
    _, k12 = dempster_combine(m1, m2)
    fused12, _ = dempster_combine(m1, m2)
    fused_seq, k3 = dempster_combine(fused12, m3)
    assert fused == pytest.approx(fused_seq)
    assert k == pytest.approx(1 - (1 - k12) * (1 - k3))


def test_dempster_batch_runs_steps():
    rng = np.random.default_rng(47)
    m1 = rng.dirichlet(np.ones(7), (30, 4))
    m2 = rng.dirichlet(np.ones(7), (30, 4))
    m1 = np.concatenate([np.zeros((30, 4, 1)), m1], axis=-1)
    m2 = np.concatenate([np.zeros((30, 4, 1)), m2], axis=-1)
    masses, conflict = dempster_combine_array(m1, m2)
    assert masses.shape == (30, 4, 8) and conflict.shape == (30, 4)
    for r, k in [(0, 0), (17, 2), (29, 3)]:
        item, kk = dempster_combine_array(m1[r, k], m2[r, k])
        np.testing.assert_allclose(masses[r, k], item, rtol=1e-13)
        assert conflict[r, k] == pytest.approx(float(kk))
    # One mass function broadcast against a batch.
    assert dempster_combine_array(m1, m2[0, 0]).masses.shape == (30, 4, 8)


def test_total_conflict_nan_mode_keeps_the_batch():
    good = mass_to_array({LEARJET: 0.5, UNKNOWN: 0.5}, CLASSES)
    only_f = mass_to_array({FALCON: 1.0}, CLASSES)
    only_l = mass_to_array({LEARJET: 1.0}, CLASSES)
    m1 = np.stack([good, only_l])
    m2 = np.stack([good, only_f])
    with pytest.raises(ValueError, match="total conflict"):
        dempster_combine_array(m1, m2)
    masses, conflict = dempster_combine_array(m1, m2, on_total_conflict="nan")
    assert np.isnan(masses[1]).all() and conflict[1] == 1.0
    assert masses[0, 0b001] == pytest.approx(0.75) and conflict[0] == 0.0
    masses3, conflict3 = dempster_combine_array(m1, m2, m1, on_total_conflict="nan")
    assert np.isnan(masses3[1]).all() and conflict3[1] == 1.0 and np.isfinite(masses3[0]).all()


# ---------------------------------------------------------------------------------------------
# Properties
# ---------------------------------------------------------------------------------------------


@st.composite
def mass_arrays(draw, n: int, batch: tuple[int, ...] = ()):
    """Random mass arrays over a frame of n classes: a few focal elements, some exact zeros."""
    size = 1 << n
    count = int(np.prod(batch, dtype=int))
    out = np.zeros((count, size))
    for i in range(count):
        focal = draw(st.lists(st.integers(1, size - 1), min_size=1, max_size=min(5, size - 1)))
        weights = draw(st.lists(st.floats(0.01, 1.0), min_size=len(focal), max_size=len(focal)))
        for f, w in zip(focal, weights, strict=True):
            out[i, f] += w
        out[i] /= out[i].sum()
    return out.reshape(batch + (size,))


def _combine_or_none(*ms):
    try:
        return dempster_combine_array(*ms)
    except ValueError as exc:
        assert "total conflict" in str(exc)
        return None


@HYPO
@given(st.integers(1, 4).flatmap(lambda n: st.tuples(mass_arrays(n), mass_arrays(n))))
def test_dempster_commutative(pair):
    m1, m2 = pair
    a, b = _combine_or_none(m1, m2), _combine_or_none(m2, m1)
    assert (a is None) == (b is None)
    if a is not None:
        np.testing.assert_allclose(a.masses, b.masses, rtol=1e-12, atol=1e-15)
        assert float(a.conflict) == pytest.approx(float(b.conflict), abs=1e-15)


@HYPO
@given(st.integers(1, 4).flatmap(lambda n: st.tuples(*[mass_arrays(n)] * 3)))
def test_dempster_associative(triple):
    m1, m2, m3 = triple
    left12 = _combine_or_none(m1, m2)
    right23 = _combine_or_none(m2, m3)
    left = None if left12 is None else _combine_or_none(left12.masses, m3)
    right = None if right23 is None else _combine_or_none(m1, right23.masses)
    assert (left is None) == (right is None)
    if left is not None:
        np.testing.assert_allclose(left.masses, right.masses, rtol=1e-9, atol=1e-12)
        three = dempster_combine_array(m1, m2, m3)
        np.testing.assert_allclose(three.masses, left.masses, rtol=1e-9, atol=1e-12)
        # The three-way conflict does not depend on the grouping either.
        k = 1 - (1 - float(left12.conflict)) * (1 - float(left.conflict))
        k_right = 1 - (1 - float(right23.conflict)) * (1 - float(right.conflict))
        assert float(three.conflict) == pytest.approx(k, abs=1e-12)
        assert k == pytest.approx(k_right, abs=1e-12)


@HYPO
@given(st.integers(1, 5).flatmap(lambda n: mass_arrays(n, (3,))))
def test_vacuous_mass_is_identity(m):
    vacuous = np.zeros(m.shape[-1])
    vacuous[-1] = 1.0
    masses, conflict = dempster_combine_array(m, vacuous)
    np.testing.assert_allclose(masses, m, rtol=1e-14, atol=1e-17)
    assert np.all(conflict == 0)


@HYPO
@given(st.integers(1, 4).flatmap(lambda n: st.tuples(st.just(n), mass_arrays(n))))
def test_belief_plausibility_relations(nm):
    n, m = nm
    full = (1 << n) - 1
    for a in range(1 << n):
        bel, pl = belief_array(m, a), plausibility_array(m, a)
        assert -1e-15 <= bel <= pl + 1e-15 <= 1 + 2e-15
        assert bel + plausibility_array(m, full ^ a) == pytest.approx(1.0, abs=1e-12)
        for b in range(1 << n):  # monotone in the subset
            if a & b == a:
                assert belief_array(m, b) >= bel - 1e-15
    assert belief_array(m, 0) == 0 and plausibility_array(m, 0) == 0
    assert belief_array(m, full) == pytest.approx(1.0)
    assert plausibility_array(m, full) == pytest.approx(1.0)
    # The dict forms agree.
    frame = [f"c{j}" for j in range(n)]
    d = array_to_mass(m, frame)
    for a in range(1 << n):
        sub = [frame[j] for j in range(n) if a >> j & 1]
        assert belief(d, sub, frame) == pytest.approx(float(belief_array(m, a)), abs=1e-15)
        assert plausibility(d, sub, frame) == pytest.approx(
            float(plausibility_array(m, a)), abs=1e-15
        )


@HYPO
@given(
    st.integers(1, 4).flatmap(
        lambda n: st.tuples(mass_arrays(n, (4,)), mass_arrays(n, (4,)), st.integers(0, 2**n - 1))
    )
)
def test_array_batch_equals_items(args):
    m1, m2, a = args
    m2 = 0.5 * m2
    m2[..., -1] += 0.5  # mass on the frame: never total conflict
    masses, conflict = dempster_combine_array(m1, m2)
    bel, pl = belief_array(masses, a), plausibility_array(masses, a)
    for i in range(4):
        item, k = dempster_combine_array(m1[i], m2[i])
        # Equal up to rounding: the batch's union of focal elements may select the other
        # (commonality) summation path than the single item does.
        np.testing.assert_allclose(masses[i], item, rtol=1e-12, atol=1e-14)
        assert conflict[i] == pytest.approx(float(k), abs=1e-14)
        assert bel[i] == pytest.approx(float(belief_array(item, a)), abs=1e-14)
        assert pl[i] == pytest.approx(float(plausibility_array(item, a)), abs=1e-14)


@HYPO
@given(st.integers(1, 5).flatmap(lambda n: st.tuples(mass_arrays(n, (3,)), mass_arrays(n, (3,)))))
def test_pairs_and_commonality_paths_agree(pair):
    m1, m2 = pair
    exact = conjunctive(m1, m2, "pairs")
    np.testing.assert_allclose(conjunctive(m1, m2, "commonality"), exact, atol=1e-13)
    assert exact.sum(axis=-1) == pytest.approx(1.0, abs=1e-12)


def test_commonality_path_large_frame():
    # 200 focal elements each over a frame of 10 classes: 40000 pairs, so Dempster's rule takes
    # the commonality route; check it against the direct sum over pairs.
    rng = np.random.default_rng(10)
    m = np.zeros((2, 3, 1024))
    for idx in np.ndindex(2, 3):
        focal = rng.choice(np.arange(1, 1024), 200, replace=False)
        m[idx][focal] = rng.dirichlet(np.ones(200))
    fast = conjunctive(m[0], m[1], "commonality")
    np.testing.assert_allclose(fast, conjunctive(m[0], m[1], "pairs"), atol=1e-13)
    masses, conflict = dempster_combine_array(m[0], m[1])
    np.testing.assert_allclose(masses.sum(-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(conflict, fast[..., 0], atol=1e-13)
    assert np.all(masses >= 0)


@HYPO
@given(
    st.integers(2, 6).flatmap(
        lambda c: st.tuples(*[st.lists(st.floats(0.01, 1), min_size=c, max_size=c)] * 2)
    )
)
def test_bayesian_masses_reduce_to_bayes(pair):
    # Masses on singletons only: Dempster's rule is the normalised product, i.e. Bayes fusion
    # with a uniform prior (eq. 37).
    p1, p2 = (np.asarray(p) / np.sum(p) for p in pair)
    c = p1.size
    frame = [f"c{j}" for j in range(c)]
    m1 = {frozenset({frame[j]}): p1[j] for j in range(c)}
    m2 = {frozenset({frame[j]}): p2[j] for j in range(c)}
    fused, conflict = dempster_combine(m1, m2, frame=frame)
    bayes = bayes_fusion(np.stack([p1, p2]), np.full(c, 1.0 / c))
    np.testing.assert_allclose([fused[frozenset({f})] for f in frame], bayes, rtol=1e-12)
    assert conflict == pytest.approx(1 - float(p1 @ p2), abs=1e-12)


# ---------------------------------------------------------------------------------------------
# Errors
# ---------------------------------------------------------------------------------------------

_GOOD = {LEARJET: 0.5, UNKNOWN: 0.5}


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: dempster_combine({LEARJET: 0.5, FALCON: 0.4}, _GOOD), "sum to"),
        (lambda: dempster_combine(_GOOD, {LEARJET: 1.2, FALCON: -0.2}), "negative"),
        (lambda: dempster_combine({frozenset(): 0.1, LEARJET: 0.9}, _GOOD), "empty set"),
        (lambda: dempster_combine(_GOOD, {frozenset({"Cessna"}): 1.0}, frame=CLASSES), "frame"),
        (lambda: dempster_combine({LEARJET: 1.0}, {FALCON: 1.0}), "total conflict"),
        (lambda: dempster_combine({"Learjet": 1.0}, _GOOD), "frozenset"),
        (lambda: dempster_combine(_GOOD, {LEARJET: float("nan"), FALCON: 1.0}), "finite"),
        (lambda: dempster_combine(_GOOD, _GOOD, frame=["a", "a", "b"]), "repeated"),
        (lambda: dempster_combine_array([0, 0.5, 0.4, 0.1], [0, 0.5, 0.4, 0.2]), "sum to"),
        (lambda: dempster_combine_array([0, 1.5, -0.5, 0], [0, 0, 0, 1]), "negative"),
        (lambda: dempster_combine_array([0.1, 0.9, 0, 0], [0, 0, 0, 1]), "empty set"),
        (lambda: dempster_combine_array([0, 1, 0, 0], [0, 0, 1, 0]), "total conflict"),
        (lambda: dempster_combine_array([0, 0.5, 0.5], [0, 0, 1]), "2\\*\\*N"),
        (lambda: dempster_combine_array([0, 0, 0, 1], np.eye(8)[7]), "different frames"),
        (lambda: dempster_combine_array(np.eye(4)[[3, 3]], np.eye(4)[[3, 3, 3]]), "batch"),
        (lambda: belief_array([0, 0, 0, 1], 4), "outside the frame"),
        (lambda: plausibility_array([0, 0, 0, 1.1], 1), "sum to"),
        (lambda: belief(_GOOD, {"Cessna"}, CLASSES), "frame"),
        (lambda: belief(_GOOD, "Learjet"), "string"),
        (lambda: plausibility({LEARJET: 0.7}, LEARJET), "sum to"),
        (lambda: subset_index({"Cessna"}, CLASSES), "frame"),
        (lambda: mass_to_array({frozenset({"Cessna"}): 1.0}, CLASSES), "frame"),
    ],
)
def test_errors(call, message):
    with pytest.raises(ValueError, match=message) as info:
        call()
    assert "\n" not in str(info.value)


def test_sum_tolerance():
    eps = MASS_TOL / 2
    dempster_combine({LEARJET: 0.5 + eps, UNKNOWN: 0.5}, _GOOD)
    with pytest.raises(ValueError, match="sum to"):
        dempster_combine({LEARJET: 0.5 + 3 * eps, UNKNOWN: 0.5}, _GOOD)
