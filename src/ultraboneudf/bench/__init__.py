"""Experiments over datasets: manifests, generators, the resumable runner and the paper's tables.

``ultraboneudf bench dataset KIND SOURCE --out DIR`` writes a dataset and its ``manifest.csv``;
``ultraboneudf bench run [EXPERIMENT] --dataset MANIFEST --out DIR`` runs its cells (resumable);
``ultraboneudf bench report DIR`` prints the tables.
"""
