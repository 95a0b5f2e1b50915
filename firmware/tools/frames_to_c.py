#!/usr/bin/env python3
"""Write the STM32 image's frames table (stm32/frames_table.c) from a frames file
(docs/formats.md#frames-file): the first ROWS rows, as float32 volts at 8 mA.

    python3 firmware/tools/frames_to_c.py FRAMES.csv firmware/stm32/frames_table.c [--rows 8] [--layers 2] [--noise V]
"""
import argparse
import sys


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("frames")
    p.add_argument("out")
    p.add_argument("--rows", type=int, default=8, help="rows kept (flash: 832 bytes each)")
    p.add_argument("--layers", type=int, default=2, choices=(1, 2), help="the pattern the rows are in")
    p.add_argument("--noise", type=float, default=0.0, help="white noise the front-end adds, volts rms")
    a = p.parse_args(argv)
    rows = []
    with open(a.frames) as f:
        for n, line in enumerate(f, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            vals = [float(x) for x in line.split(",")]
            if len(vals) != 208:
                print(f"frames_to_c: {a.frames} line {n}: {len(vals)} values; expected 208", file=sys.stderr)
                return 2
            rows.append(vals)
            if len(rows) == a.rows:
                break
    if not rows:
        print(f"frames_to_c: {a.frames}: no frame in it", file=sys.stderr)
        return 2
    out = [f"/* {len(rows)} frames of {a.frames} (written by firmware/tools/frames_to_c.py) */",
           "#include <stdint.h>", "",
           f"const uint32_t cstomo_n_frames = {len(rows)};",
           f"const uint8_t cstomo_frames_layers = {a.layers};",
           f"const float cstomo_noise_v = {a.noise!r}f;",
           f"const float cstomo_frames[{len(rows)}][208] = {{"]
    for r in rows:
        out.append("    {" + ",".join(f"{v:.9e}f" for v in r) + "},")
    out.append("};")
    with open(a.out, "w") as f:
        f.write("\n".join(out) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
