"""Everything about the ball-bar verification of a calibration (thesis 6.9.3, VDI/VDE 2634):
where to put the bar (:mod:`.plan`), finding and fitting its spheres in every scanner
(:mod:`.ballbar`, :mod:`.measure`), its lengths and their evaluation (:mod:`.lengths`), and
each length's uncertainty budget (:mod:`.budget`, :mod:`.uncertainty`)."""
