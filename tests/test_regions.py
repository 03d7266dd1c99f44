"""a3cqp_rl.regions: the literal Fig. 5 check and the contrast check on hand-built policies."""

import pytest
import torch

from a3cqp_rl.regions import LITERAL_COLUMNS, REGION_COLUMNS, check_fig5_regions, format_regions, region_row

IK, ADM, FC = (1.0, -1.0, -1.0, -1.0), (-1.0, 1.0, -1.0, -1.0), (-1.0, -1.0, 1.0, 1.0)


def rule_policy(obs):
    """The Fig. 5 pattern written by hand: admittance under an operator, force control in contact, IK when free."""
    e, fe, fo = obs.unbind(-1)
    out = torch.tensor(IK).expand(*obs.shape[:-1], 4).clone()
    out[fe > 0.1] = torch.tensor(FC)
    out[fo > 0.1] = torch.tensor(ADM)
    out[(fe <= 0.1) & (fo <= 0.1) & (e < 0.05)] = 0.0
    return out


def by_name(results):
    return {r.short: r for r in results}


def test_the_fig5_pattern_passes_both_checks():
    res = by_name(check_fig5_regions(rule_policy))
    assert all(r.literal and r.ok for r in res.values()), res
    assert res["w2"].rates_inside == pytest.approx((-1.0, 1.0, -1.0, -1.0))
    assert region_row(rule_policy) == dict.fromkeys(REGION_COLUMNS, 1.0) | {"regions_ok": 4.0, "literal_ok": 4.0}


def test_force_control_raised_under_the_operator_passes_the_contrast_but_not_the_literal_check():
    """The failure the literal check exists for: under the operator ẇ2 rises (contrast holds) but ẇ3 rises more."""
    def policy(obs):
        a = rule_policy(obs)
        pushes = (obs[..., 2] >= 0.5) & (obs[..., 1] <= 0.05)
        a[pushes] = torch.tensor([-1.0, 0.6, 0.8, -1.0])
        return a

    w2 = by_name(check_fig5_regions(policy))["w2"]
    assert w2.ok and not w2.literal, w2


def test_negative_rate_fails_literal_and_constant_policies_fail_the_contrast():
    def no_fd(obs):
        a = rule_policy(obs)
        a[..., 3] = -0.2
        return a

    res = by_name(check_fig5_regions(no_fd))
    assert not res["fd"].literal and not res["fd"].ok and res["w3"].literal
    # IK everywhere: the IK region passes the literal check (ẇ1 is the highest rate there) but no contrast
    ik = by_name(check_fig5_regions(lambda o: torch.tensor(IK).expand(*o.shape[:-1], 4)))
    assert ik["w1"].literal and not ik["w1"].ok
    assert not ik["w2"].literal and not ik["w3"].literal and not ik["fd"].literal
    row = region_row(lambda o: torch.tensor(IK).expand(*o.shape[:-1], 4))
    assert row["literal_ok"] == 1.0 and row["regions_ok"] == 0.0 and set(LITERAL_COLUMNS) <= set(row)


def test_ties_are_not_higher_and_text_shows_both_checks():
    equal = by_name(check_fig5_regions(lambda o: torch.full((*o.shape[:-1], 4), 0.5)))
    assert not any(r.literal for r in equal.values() if r.short != "fd") and equal["fd"].literal
    text = format_regions(check_fig5_regions(rule_policy))
    assert "literal 4/4, contrast 4/4" in text and text.count("ok") == 8
    with pytest.raises(ValueError, match=r"actions \[B, 4\]"):
        check_fig5_regions(lambda o: o)
