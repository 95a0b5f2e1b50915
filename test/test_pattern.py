"""The generated measurement order against the paper's appendix B and C tables (legible rows)."""
import pytest

from cstomo_sensor.model.pattern import MeasurementPattern

# (row, drive pair, measure pair), 1-based, transcribed from the paper's appendix B (one layer).
# "20 6,7 8,9" is printed with a garbled row number: it is row 70 (docs/physics.md#measurement-order).
APPENDIX_B = """
1 1,2 3,4; 2 1,2 4,5; 5 1,2 7,8; 13 1,2 15,16; 14 2,3 4,5; 25 2,3 15,16; 26 2,3 16,1;
27 3,4 1,2; 28 3,4 5,6; 39 3,4 16,1; 40 4,5 1,2; 41 4,5 2,3; 42 4,5 6,7; 52 4,5 16,1;
53 5,6 1,2; 54 5,6 2,3; 55 5,6 3,4; 56 5,6 7,8; 65 5,6 16,1; 66 6,7 1,2; 69 6,7 4,5; 70 6,7 8,9;
78 6,7 16,1; 79 7,8 1,2; 83 7,8 5,6; 84 7,8 9,10; 91 7,8 16,1; 92 8,9 1,2; 97 8,9 6,7;
98 8,9 10,11; 100 8,9 12,13; 104 8,9 16,1; 111 9,10 7,8; 112 9,10 11,12; 117 9,10 16,1;
118 10,11 1,2; 125 10,11 8,9; 126 10,11 12,13; 130 10,11 16,1; 131 11,12 1,2; 139 11,12 9,10;
140 11,12 13,14; 143 11,12 16,1; 144 12,13 1,2; 153 12,13 10,11; 154 12,13 14,15;
156 12,13 16,1; 157 13,14 1,2; 167 13,14 11,12; 168 13,14 15,16; 169 13,14 16,1; 170 14,15 1,2;
181 14,15 12,13; 182 14,15 16,1; 183 15,16 1,2; 195 15,16 13,14; 196 16,1 2,3; 208 16,1 14,15
"""
# Appendix C (two layers). "103 9,10 1,2" is row 105. Rows 181 and 195 are misprinted in the paper
# (they measure across a driven electrode); the rule gives (12,13) and (13,14), listed here.
APPENDIX_C = """
1 1,2 3,4; 2 1,2 4,5; 5 1,2 7,8; 6 1,2 9,10; 12 1,2 15,16; 13 1,2 16,9; 14 2,3 4,5; 17 2,3 7,8;
18 2,3 8,1; 19 2,3 9,10; 26 2,3 16,9; 27 3,4 1,2; 28 3,4 5,6; 30 3,4 7,8; 31 3,4 8,1;
32 3,4 9,10; 39 3,4 16,9; 40 4,5 1,2; 41 4,5 2,3; 42 4,5 6,7; 43 4,5 7,8; 44 4,5 8,1;
45 4,5 9,10; 52 4,5 16,9; 53 5,6 1,2; 55 5,6 3,4; 66 6,7 1,2; 69 6,7 4,5; 70 6,7 8,1;
71 6,7 9,10; 78 6,7 16,9; 79 7,8 1,2; 83 7,8 5,6; 84 7,8 9,10; 91 7,8 16,9; 92 8,1 2,3;
96 8,1 6,7; 97 8,1 9,10; 100 8,1 12,13; 104 8,1 16,9; 105 9,10 1,2; 112 9,10 8,1;
113 9,10 11,12; 117 9,10 15,16; 118 10,11 1,2; 125 10,11 8,1; 126 10,11 12,13; 130 10,11 16,9;
131 11,12 1,2; 139 11,12 9,10; 140 11,12 13,14; 143 11,12 16,9; 144 12,13 1,2;
153 12,13 10,11; 154 12,13 14,15; 156 12,13 16,9; 157 13,14 1,2; 167 13,14 11,12;
168 13,14 15,16; 169 13,14 16,9; 170 14,15 1,2; 181 14,15 12,13; 182 14,15 16,9; 183 15,16 1,2;
195 15,16 13,14; 196 16,9 1,2; 203 16,9 8,1; 204 16,9 10,11; 208 16,9 14,15
"""


def _rows(table):
    out = []
    for item in table.replace("\n", " ").split(";"):
        n, d, m = item.split()
        out.append((int(n), tuple(map(int, d.split(","))), tuple(map(int, m.split(",")))))
    return out


@pytest.mark.parametrize("layers,table", [(1, APPENDIX_B), (2, APPENDIX_C)])
def test_pattern_reproduces_paper_tables(layers, table):
    p = MeasurementPattern(16, layers)
    assert p.n_meas == 208
    rows = _rows(table)
    assert len(rows) > 55
    for n, drive, meas in rows:
        assert tuple(p.drive[n - 1] + 1) == drive, f"row {n}"
        assert tuple(p.measure[n - 1] + 1) == meas, f"row {n}"


@pytest.mark.parametrize("layers", [1, 2])
def test_no_measurement_touches_a_driven_electrode(layers):
    p = MeasurementPattern(16, layers)
    for d, m in zip(p.drive, p.measure):
        assert not set(d) & set(m)
    # every (drive, measure) pair is used once, and reciprocal pairs both appear
    keys = {tuple(r) for r in p.rows}
    assert len(keys) == 208 and all((b, a) in keys for a, b in keys)
