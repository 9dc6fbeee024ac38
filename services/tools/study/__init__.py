"""``nwr study``: the paper's protocol on the live pipeline (:mod:`.main`), its answer store (:mod:`.store`), its
questionnaires as web pages (:mod:`.web`) and its analysis (:mod:`.analysis`)."""
