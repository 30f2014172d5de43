"""cmr.paired: case-by-case comparison of two evaluations of the same cases."""

import json

import pytest

from cmr.paired import compare, finals, main


def case(seq, frame, rte, rre, method="cmr-agent"):
    return dict(sequence=seq, frame=frame, method=method, errors=[dict(rte_m=99.0, rre_euler_deg=99.0),
                                                                   dict(rte_m=rte, rre_euler_deg=rre)])


def write(path, cases):
    path.mkdir(parents=True)
    (path / "cases.json").write_text(json.dumps(cases))


def test_counts_cases_only_one_side_registers_on_the_final_answer(tmp_path, capsys):
    a = [case("00", 0, 1.0, 2.0), case("00", 1, 6.0, 2.0), case("01", 0, 2.0, 3.0), case("01", 1, 3.0, 11.0),
         case("00", 0, 0.1, 0.1, method="no-op")]
    b = [case("00", 0, 3.0, 1.0), case("00", 1, 4.0, 9.0), case("01", 0, 9.0, 1.0), case("01", 1, 1.0, 1.0),
         case("00", 0, 50.0, 90.0, method="no-op")]
    write(tmp_path / "A" / "f", a)
    write(tmp_path / "B" / "f", b)
    r = compare(finals(tmp_path / "A" / "f" / "cases.json"), finals(tmp_path / "B" / "f" / "cases.json"))
    assert r == dict(cases=4, a=2, b=3, only_a=1, only_b=2, both=1, rte_a=1.0, rte_b=3.0)
    main([str(tmp_path / "A"), str(tmp_path / "B"), "f"])
    assert "| **pooled** | 4 | 2 | 3 | 1 / 2 | 1.00 / 3.00 |" in capsys.readouterr().out


def test_refuses_different_cases(tmp_path):
    with pytest.raises(ValueError, match="different cases"):
        compare([(("00", 0), {})], [(("00", 1), {})])
