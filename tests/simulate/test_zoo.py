"""The chain zoo: seeded random chains covering both regimes Eq. 2 describes."""

import numpy as np
import pytest

from bayes_tfcrds.physics.detection_chain import chain_from_tf
from bayes_tfcrds.physics.transfer_function import transfer_function
from bayes_tfcrds.simulate.zoo import CRITICAL_GAP, ZOO_RANGES, draw_chain, zoo_chains


@pytest.mark.parametrize("regime", sorted(ZOO_RANGES))
def test_draws_stay_in_their_ranges_and_are_valid_chains(regime):
    rng = np.random.default_rng(3)
    r = ZOO_RANGES[regime]
    for _ in range(200):
        tf = draw_chain(rng, regime)
        assert r.f_c_hz[0] <= tf.f_c_hz <= r.f_c_hz[1]
        assert r.a_r[0] <= tf.a_r <= r.a_r[1]
        assert r.f_r_hz[0] <= tf.f_r_hz <= r.f_r_hz[1]
        assert abs(tf.gamma_r - 0.5) >= CRITICAL_GAP
    # the rational chain the simulator builds is Eq. 2 itself (unit DC gain, same response)
    f = np.logspace(3, 7.6, 50)
    h = chain_from_tf(tf).frequency_response(f)
    np.testing.assert_allclose(h, transfer_function(f, tf), rtol=1e-9)


def test_pole_regime_puts_the_resonance_on_both_sides_of_f_c():
    rng = np.random.default_rng(4)
    ratios = np.array([tf.f_r_hz / tf.f_c_hz for _, tf in zoo_chains(rng, 200, ("pole",))])
    assert (ratios < 1).mean() > 0.5 and (ratios > 1).mean() > 0.05


def test_same_seed_same_zoo_and_regimes_in_turn():
    a = zoo_chains(np.random.default_rng(9), 6)
    b = zoo_chains(np.random.default_rng(9), 6)
    assert a == b
    assert [reg for reg, _ in a] == ["tail", "pole"] * 3
    with pytest.raises(ValueError, match="unknown chain regime"):
        draw_chain(np.random.default_rng(0), "other")
