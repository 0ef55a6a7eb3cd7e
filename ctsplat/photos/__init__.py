"""The sanity run on ordinary photographs: photos -> COLMAP poses (:mod:`.sfm`) -> alpha-composited 3DGS with SH
colour (:mod:`.train`) -> held-out metrics, gallery and turntable (:mod:`.evaluate`).

Settings: :mod:`.config`; the photo folder: :mod:`.images`; an SfM folder as training data: :mod:`.dataset`;
densification for alpha compositing: :mod:`.densify`.
"""
