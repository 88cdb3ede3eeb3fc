"""Pictures framed as users take them, from renders framed as the image model's training views.

Usage: picture-variants.py VARIANT SRC_DIR OUT_DIR, where SRC_DIR holds the square PNG renders
`scripts/evaluate-image.sh` makes (white background) and VARIANT is one of
  tight      a product shot cropped to the object with a 4% margin, 512 x 512;
  offcentre  the object at a random place on a 640 x 480 white landscape picture;
  offjpeg    the same as a JPEG of quality 80;
  greybg     the render with its background a light studio grey;
  colour     the object in a colour of its own (red, navy, near-black, wood, yellow, green),
             as the renderer would have shaded it: the training renders are all light grey.
The places and colours are drawn from seeds of their own in name order, so a variant is the
same on every run.
"""

import io
import os
import sys

import numpy as np
from PIL import Image

VARIANTS = ("tight", "offcentre", "offjpeg", "greybg", "colour")
# The renderer's base colour (render::Coloring's default), which shading scales per pixel.
RENDER_BASE = np.array([200, 200, 210])
COLOURS = np.array(
    [(170, 35, 35), (35, 45, 95), (45, 45, 48), (125, 85, 50), (225, 185, 45), (45, 115, 60)]
)


def main(variant: str, src: str, out: str) -> None:
    if variant not in VARIANTS:
        sys.exit(f"variant must be one of {', '.join(VARIANTS)}, got {variant!r}")
    os.makedirs(out, exist_ok=True)
    rng = np.random.default_rng(7)
    colour_rng = np.random.default_rng(11)
    for file in sorted(f for f in os.listdir(src) if f.endswith(".png")):
        name = file[:-4]
        image = Image.open(os.path.join(src, file)).convert("RGB")
        pixels = np.asarray(image).astype(int)
        mask = np.abs(pixels - 255).max(axis=2) > 8
        ys, xs = np.nonzero(mask)
        if len(xs) == 0:
            continue
        x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
        obj = image.crop((x0, y0, x1, y1))
        # Drawn for every picture, whatever the variant, so that the places do not depend on it.
        width, height = 640, 480
        ox = int(rng.integers(0, width - (x1 - x0) + 1))
        oy = int(rng.integers(max(0, (height - (y1 - y0)) // 4), height - (y1 - y0) + 1))
        if variant == "tight":
            side = int(max(x1 - x0, y1 - y0) * 1.08)
            canvas = Image.new("RGB", (side, side), (255, 255, 255))
            canvas.paste(obj, ((side - (x1 - x0)) // 2, (side - (y1 - y0)) // 2))
            canvas.resize((512, 512), Image.LANCZOS).save(os.path.join(out, name + ".png"))
        elif variant in ("offcentre", "offjpeg"):
            canvas = Image.new("RGB", (width, height), (255, 255, 255))
            canvas.paste(obj, (ox, oy))
            if variant == "offcentre":
                canvas.save(os.path.join(out, name + ".png"))
            else:
                buffer = io.BytesIO()
                canvas.save(buffer, "JPEG", quality=80)
                with open(os.path.join(out, name + ".jpg"), "wb") as f:
                    f.write(buffer.getvalue())
        elif variant == "colour":
            colour = COLOURS[colour_rng.integers(len(COLOURS))]
            recoloured = pixels.copy()
            recoloured[mask] = np.clip(np.rint(pixels[mask] * colour / RENDER_BASE), 0, 255)
            Image.fromarray(recoloured.astype(np.uint8)).save(os.path.join(out, name + ".png"))
        else:
            grey = pixels.copy()
            grey[~mask] = (222, 224, 230)
            Image.fromarray(grey.astype(np.uint8)).save(os.path.join(out, name + ".png"))


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    main(*sys.argv[1:])
