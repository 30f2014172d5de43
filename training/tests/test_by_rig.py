from cmr.by_rig import axes, table


def test_recall_per_rig_uses_protocol_a():
    def case(seq, method, rte, rre):
        return dict(sequence=seq, method=method, errors=[dict(rte_m=9.0, rre_euler_deg=90.0), dict(rte_m=rte, rre_euler_deg=rre)])

    rows = table([case("00", "cmr-agent", 1.0, 2.0), case("01", "cmr-agent", 4.9, 10.0), case("02", "no-op", 3.0, 4.0)],
                 {"00": "a", "01": "a"})
    assert rows[2] == "| ? | no-op | 1 | 100.0 % (1) | 3.00 m / 4.0° |"
    # the final error counts, and 10 deg Euler sum is not registered (strict, as eval counts it)
    assert rows[3] == "| a | cmr-agent | 2 | 50.0 % (1) | 1.00 m / 2.0° |"


def test_offsets_along_the_heading_and_sideways():
    # Truth: a level camera at the map origin looking along map +x (x right = map -y, y down).
    truth = [[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0]]

    def case(dx, dy, rte=1.0):
        # The answer's camera centre at map (dx, dy, 0): t = -R c.
        answer = [row[:3] + [-(row[0] * dx + row[1] * dy)] for row in truth]
        return dict(sequence="00", method="cmr-agent", errors=[dict(rte_m=rte, rre_euler_deg=1.0)],
                    notes=dict(answer_camera_from_map=answer, truth_camera_from_map=truth))

    # 2 m ahead, 1 m to the left (map +y is left of a camera looking along +x); the unregistered
    # case and one of another method do not count.
    rows = axes([case(2.0, 1.0), case(1.0, -1.0), case(0.0, 9.0, rte=9.0), dict(case(5.0, 5.0), method="no-op")], {"00": "a"})
    assert rows[2] == "| a | 2 | 1.50 m (+1.50) | 1.00 m (+0.00) |"
    rows = axes([case(0.0, 1.0)], {"00": "a"})
    assert rows[2] == "| a | 1 | 0.00 m (+0.00) | 1.00 m (-1.00) |"
