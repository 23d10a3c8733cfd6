"""Models: the nominal and perturbed systems and their simulation (`systems`), realistic
simulated plants (`plants`), the zoo of random systems (`zoo`), and the updated twin that
predicts (`prediction`)."""
