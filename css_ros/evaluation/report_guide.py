"""report.md's explanations: what U_var, U_exp, E, Var and evidence mean, how to read the plots, what is good."""
from __future__ import annotations

#: Markdown lines of the section "How to read the uncertainty numbers".
TERMS = [
    "## How to read the uncertainty numbers", "",
    "- **E** (expectation): at a pixel, the map's probability of the label it renders there (the "
    "κ-weighted mean of the Gaussians' Dirichlet means of that class). 1 means all the evidence agrees; it is a "
    "label frequency, not a calibrated probability.",
    "- **Var** (variance): how unsure the map is of that probability. Large where the Gaussians behind the pixel "
    "were seen rarely or received conflicting labels; it falls like 1 / (number of observations).",
    "- **evidence** (observation count): the κ-weighted Dirichlet total of the Gaussians behind the pixel, i.e. how "
    "many labelled pixels they absorbed. It is the baseline the paper compares against: often seen is not the "
    "same as right (a surface mislabelled the same way in every view has a large evidence).",
    "- **U_var** (per image): exp(mean over the pixels of log Var of the label), the geometric mean of the variance. "
    "High for views of poorly observed surfaces; a planner takes the candidate view with the highest U_var "
    "(or the highest information gain).",
    "- **U_exp** (per image): 1 − mean over the pixels of E of the label, the share of labels the map itself "
    "expects to be wrong.",
    "- **calibrated confidence** (`~/confidence`, only with a sensor model): the probability that the rendered "
    "label is right, fitted by css_calibrate on held-out frames from E and the evidence.",
    "- **Spearman ρ** of U_var or U_exp against the per-image error: +1 ranks the images exactly by their error, 0 "
    "not at all. Good: clearly positive (above about +0.5).",
    "",
    "**Sparsification** (pixel and image level): sort the pixels (images) from most to least uncertain, remove "
    "the most uncertain fraction x and plot the error of the rest. A useful uncertainty falls steeply: it removes "
    "the wrong labels first. The oracle (remove exactly the wrong pixels first) is the best possible curve; a "
    "random ordering stays flat at the overall error. **AUSE** is the area between a curve and the oracle's: 0 is "
    "perfect, the random ordering's AUSE means no information. Good: a small fraction of the random AUSE; a signal "
    "at or above random says nothing about where the errors are.",
    "",
    "**Reliability diagram**: the pixels are put in 15 equal bins of the predicted probability that the label is "
    "right (x); each point is the share of them actually right (y), its size the number of pixels in the bin (the "
    "histogram under it counts them). On the diagonal the probability means what it says; below it the map is "
    "overconfident, above it underconfident. A small point is a nearly empty bin and carries little weight. **ECE** "
    "(expected calibration error) is the pixel-weighted mean distance from the diagonal: 0 is perfect; below about "
    "0.05 is good, above 0.1 the values should not be read as probabilities. **Brier** score: mean squared error "
    "of the probability against right/wrong (0 is perfect).",
]

#: Caption under each plot of report.md (file name -> one paragraph).
CAPTIONS = {
    "sparsification.png": "Steeper and lower is better; the dotted oracle is the best possible curve, the dashed "
                          "random ordering the reference with no information (AUSE in the legend; see \"How to read "
                          "the uncertainty numbers\").",
    "image_uncertainty.png": "One point per evaluated frame: a useful image-level uncertainty rises with the "
                             "frame's error (Spearman ρ in the title; good above about +0.5).",
    "reliability.png": "Points on the dashed diagonal are calibrated; the point size is the number of pixels in the "
                       "bin (a small point is a nearly empty bin), the histogram below counts them. ECE in the "
                       "legend: 0 is perfect, below about 0.05 good.",
    "birdseye.png": "The map seen from above: every observed Gaussian in the colour of its most likely class; white "
                    "is unobserved (no Gaussian there received a label).",
}
