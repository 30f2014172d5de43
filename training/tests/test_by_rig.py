from cmr.by_rig import table


def test_recall_per_rig_uses_protocol_a():
    def case(seq, method, rte, rre):
        return dict(sequence=seq, method=method, errors=[dict(rte_m=9.0, rre_euler_deg=90.0), dict(rte_m=rte, rre_euler_deg=rre)])

    rows = table([case("00", "cmr-agent", 1.0, 2.0), case("01", "cmr-agent", 4.9, 10.0), case("02", "no-op", 3.0, 4.0)],
                 {"00": "a", "01": "a"})
    assert rows[2] == "| ? | no-op | 1 | 100.0 % (1) | 3.00 m / 4.0° |"
    # the final error counts, and 10 deg Euler sum is not registered (strict, as eval counts it)
    assert rows[3] == "| a | cmr-agent | 2 | 50.0 % (1) | 1.00 m / 2.0° |"
