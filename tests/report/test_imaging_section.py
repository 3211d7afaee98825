"""The report's camera-imaging section (recon/report/html.py): kept terms with gain and SE."""

from recon.report.html import Page, render_page


def test_imaging_section_lists_kept_terms_with_gain_and_se():
    sel = {"chosen": ["flash_offset"], "criterion": "keep when gain > 2 SE", "metric": "mean |Phi|",
           "values": {"terms": ["flash_offset"], "flash_offset": [0.19, 0.0, 0.0]},
           "candidates": [{"step": "ideal", "terms": [], "heldout_error": 0.1, "gain": None, "se": None},
                          {"step": "flash_offset", "terms": ["flash_offset"], "heldout_error": 0.08, "gain": 0.0175,
                           "se": 0.0021, "accepted": True},
                          {"step": "exposure", "terms": ["flash_offset", "exposure"], "heldout_error": 0.081,
                           "gain": -0.0002, "se": 0.0001, "accepted": False}]}
    page = render_page(Page(capture="c", preset="draft", imaging_selection=sel))
    assert "Camera imaging" in page and "Kept: <b>flash_offset</b>" in page
    assert "0.0175" in page and "0.0021" in page and "rejected" in page and "kept" in page
    assert "Camera imaging" not in render_page(Page(capture="c", preset="draft"))


def test_imaging_loop_section_names_the_stage_and_terms():
    ev = {"after_stage": 0, "chosen": ["exposure"], "criterion": "keep when gain > 2 SE", "metric": "mean |Phi|",
          "values": {"terms": ["exposure"], "exposure_gains": [0.9, 1.1]},
          "candidates": [{"step": "ideal", "terms": [], "heldout_error": 0.1, "gain": None, "se": None},
                         {"step": "exposure", "terms": ["exposure"], "heldout_error": 0.07, "gain": 0.03,
                          "se": 0.002, "accepted": True}]}
    page = render_page(Page(capture="c", preset="balanced", imaging_loop=ev))
    assert "in the shape&#x27;s optimization" in page and "stage 0" in page and "Kept: <b>exposure</b>" in page
