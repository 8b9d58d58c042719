"""One way to print a number with its uncertainty (GUM 7.2.6), shared by every report."""

import pytest

from identify.notation import at_place, concise, decimal_place, plus_minus, rounded, significant, unit_text


@pytest.mark.parametrize("value, std, text", [
    (5.9088, 0.0413, "5.909 ± 0.041 bar"), (509.94, 12.3, "510 ± 12 bar"), (0.85, 0.0996, "0.85 ± 0.10 bar"),
    (7.0, None, "7 bar"),
])
def test_plus_minus_rounds_the_std_to_two_digits_and_the_value_to_its_place(value, std, text):
    assert plus_minus(value, std, "bar") == text


def test_a_tiny_value_keeps_a_common_exponent_and_a_unicode_unit():
    assert plus_minus(2.5e-12, 1.3e-14, "m^2") == "(2.500 ± 0.013)×10⁻¹² m²"


@pytest.mark.parametrize("value, std, cells", [
    (5.9088, 0.0413, ("5.909", "0.041")), (1234.4, 370.0, ("1230", "370")), (3.0, float("nan"), ("3", "—")),
])
def test_rounded_gives_two_cells_at_the_same_place(value, std, cells):
    assert rounded(value, std) == cells


def test_a_limit_takes_the_place_of_the_value_beside_it():
    assert at_place(67.4645, decimal_place(0.21)) == "67.46"
    assert at_place(91.2755, decimal_place(37.0)) == "91"


def test_concise_matches_plus_minus():
    assert concise(0.85006, 6.0e-5) == "0.850060(60)"


@pytest.mark.parametrize("declared, shown", [("m^2", "m²"), ("s^-1", "s⁻¹"), ("N*s/m", "N·s/m"), ("K", "K")])
def test_units_are_shown_as_people_write_them(declared, shown):
    assert unit_text(declared) == shown


@pytest.mark.parametrize(("value", "text"), [(568.08, "570"), (0.000321, "0.00032"), (1.0874, "1.1"),
                                             (13.98, "14"), (-0.0456, "-0.046"), (0.0, "0")])
def test_a_number_without_uncertainty_keeps_two_significant_digits_and_no_exponent(value, text):
    assert significant(value) == text


def test_an_expanded_uncertainty_is_k_times_the_sigma_shown_beside_it():
    """'6.005 ± 0.041 bar' was printed beside σ '0.021 bar' (each rounded on its own)."""
    from identify.notation import expanded

    assert expanded(6.00512, 0.0205, 2.0, "bar") == ("6.005 ± 0.042 bar", "0.021 bar")
    assert expanded(344.12, 2.04, 2.0, "N") == ("344.1 ± 4.0 N", "2.0 N")
    assert expanded(65.61234, 0.5123, 2.0, "J") == ("65.61 ± 1.02 J", "0.51 J")
    assert expanded(1.5, float("nan"), 2.0, "N") == ("1.5 N", "—")
