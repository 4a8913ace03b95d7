"""What a run is: its configuration (:mod:`.config`), what it records about itself and its
verdict (:mod:`.summary`), how an interrupted run resumes (:mod:`.resume`), and the kernel
warm-up of a first run (:mod:`.warmup`)."""
